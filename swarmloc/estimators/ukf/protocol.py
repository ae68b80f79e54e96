"""The UKF-DCL protocol's constants, shared by the node (dcl.py), its chain steps (chains.py) and
its commit history (commits.py)."""

Key = tuple[int, int, int, int]
NEIGHBOUR_TICKS = 3
VERSION_RETRIES = 2  # chain reruns when m and n are at different versions
LOG_COMMITS = 2048  # applied commits kept to replay to nodes that missed them
LOG_BATCH = 16  # commits per dcl.log frame
GIVE_UP_TICKS = 40  # a commit whose history never arrives makes the node an orphan after this
BUSY_RETRIES = 4  # bounded chains: reruns of a measurement whose measured platform was in another chain
MAX_QUEUED = 64  # bounded chains: starts waiting at a busy measured platform
HOLD_TICKS = 10  # real time: longest wait for the commit of a chain we reported to
# Real time: the unit of a chain step's timeout, a share of the tick (docs/ukf-dcl.md, "Timeouts").
HOP_TIMEOUT_TICKS = 1 / 64


