"""Records the wire corpus tests/test_wire_corpus.py holds the codec to.

    python tests/data/record_wire.py    # writes tests/data/wire_corpus.msgpack.gz

Two parts, both with what the decoder of the time made of them:
- frames: every frame of in-process runs of each estimator family's scenario (the radio
  frames the nodes send, and the sensors, clock, truth, estimate, done, links and command
  frames netsim and the agents would publish for the same run), each with its decoded value;
- refusals: hostile inputs from the fuzz generators (tests/test_fuzz.py) with fixed seeds,
  each with the decoder's verdict (the decoded value, or the error's class and reason).

The file in the repository was recorded with the hand-written schema layer, before the codec
moved to msgspec (this script and the two time.* samples of tests/test_fuzz.py copied into a
checkout of it, then run there), so the test proves the msgspec codec reads every frame to the
same values, writes the same bytes, and refuses what the old one refused. The checkout was
cc2dc01, a commit of the main that sessions 30-33 worked on, whose work reached this repository
as one change (700aaee): it is not in this history (the file says "main cc2dc01"). Here that
codec is 1cc5259's (swarmloc/wire.py and swarmloc/messages.py), which reads all 17,556
recorded frames to the recorded values and bytes and gives all 5,202 hostile inputs the
recorded verdict and reason, except for the two types cc2dc01 had and 1cc5259 has not yet
(time.echo and time.sync: 2 frames and the 154 inputs that carry them). To record again, run
this script in a checkout of 1cc5259 with those two types added.
"""

from __future__ import annotations

import gzip
import hashlib
import math
import random
import struct
import sys
from pathlib import Path

import msgpack
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # tests/: the fuzz generators

from netsim.sim import Simulation  # noqa: E402
from swarmloc import wire  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner, make_nodes  # noqa: E402
from swarmloc.node import estimate_of  # noqa: E402
from swarmloc.wire import messages as M  # noqa: E402

OUT = HERE / "wire_corpus.msgpack.gz"


def canon(v):
    """A decoded value as plain MessagePack data that keeps every distinction the decoder makes:
    int vs float vs bool, float bits (NaN too), array dtype, shape and bits (as a hash of
    its bytes, which the frame holds anyway), field order."""
    if isinstance(v, wire.Envelope):
        return ["env", v.type, v.src, v.seq, v.dst, canon(v.body)]
    if isinstance(v, np.ndarray):
        return ["nd", v.dtype.str, list(v.shape), hashlib.blake2b(v.tobytes(), digest_size=16).digest()]
    if hasattr(v, "TYPE"):  # a message
        names = getattr(v, "__struct_fields__", None) or tuple(v.__dataclass_fields__)
        return ["msg", v.TYPE, [[f, canon(getattr(v, f))] for f in names]]
    if isinstance(v, bool):
        return ["b", v]
    if isinstance(v, int):
        return ["i", v]
    if isinstance(v, float):
        return ["f", struct.pack("<d", v)]
    if isinstance(v, dict):
        return ["map", [[canon(k), canon(x)] for k, x in v.items()]]
    if isinstance(v, list):
        return ["list", [canon(x) for x in v]]
    if v is None or isinstance(v, (str, bytes)):
        return ["raw", v]
    if isinstance(v, msgpack.ExtType):  # only in a body left undecoded (body=False)
        return ["ext", v.code, v.data]
    if isinstance(v, msgpack.Timestamp):
        return ["ts", v.seconds, v.nanoseconds]
    raise TypeError(f"cannot canonicalise {type(v).__name__}")


def verdict(data: bytes, body: bool = True):
    try:
        return ["ok", canon(wire.decode(data, body=body))]
    except wire.WireError as exc:
        return ["err", type(exc).__name__, str(exc)]


def planar_pose(estimator: str):
    from test_fuzz import pose_robots

    return pose_robots(estimator).with_overrides(**{"clock.duration": 4.0})


# case -> (estimator, scenario, ticks of netsim/agent frames recorded beside the radio frames)
CASES = {
    "ukf-dcl/wang2019": ("ukf-dcl", lambda: S.load("wang2019"), 60),  # the whole 400 s run's radio
    "ukf-dcl/pose": ("ukf-dcl", lambda: planar_pose("ukf-dcl"), 9),
    "csl-ctl/wang2022": ("csl-ctl", lambda: S.load("wang2022").with_overrides(**{"clock.duration": 110.0}), 20),
    "il-ctl/wang2022": ("il-ctl", lambda: S.load("wang2022").with_overrides(**{"clock.duration": 110.0}), 20),
    "dnbp/wan2014": ("dnbp", lambda: S.load("wan2014").with_overrides(
        **{"clock.duration": 3.0, "estimator.params": {"M": 100, "iterations": 2}}), 4),
    "ekf-centre/goel2node": ("ekf-centre", lambda: S.load("goel2node").with_overrides(**{"clock.duration": 3.0}), 30),
    "ekf-ci/goel-dist": ("ekf-ci", lambda: S.load("goel-dist").with_overrides(
        **{"clock.duration": 3.0, "sensors.epoch": 0.2}), 30),
    "ekf-naive/goel-dist": ("ekf-naive", lambda: S.load("goel-dist").with_overrides(
        **{"clock.duration": 1.0, "sensors.epoch": 0.2}), 5),
    "ekf-ci/pose": ("ekf-ci", lambda: planar_pose("ekf-ci"), 9),
    "ekf-cl/oliveros3": ("ekf-cl", lambda: S.load("oliveros3").with_overrides(
        **{"clock.duration": 1.0, "world.control": "agents"}), 51),
    "ekf-local/caravan": ("ekf-local", lambda: S.load("oliveros-caravan-control-1").with_overrides(
        **{"clock.duration": 0.5, "world.control": "agents", "estimator": {"name": "ekf-local", "params": {}}}), 26),
    "ekf-ci/caravan": ("ekf-ci", lambda: S.load("oliveros-caravan-2").with_overrides(
        **{"clock.duration": 0.5, "estimator": {"name": "ekf-ci", "params": {}}}), 26),
}


def record_case(name: str, algorithm: str, sc, side_ticks: int) -> list:
    """[case, key, frame, decoded] for every frame of the run."""
    out: list = []
    real_encode = wire.encode

    def radio(msg, src, seq, dst=None):  # the nodes' frames (Outbox) and the runner's commands
        data = real_encode(msg, src, seq, dst)
        out.append([name, "command" if msg.TYPE == "command" else "radio", data])
        return data

    sim = Simulation(sc)
    nodes = make_nodes(algorithm, sc)
    seq = {"netsim": 0}
    handled = {a: 0 for a in nodes}

    def netsim(msg, key):
        seq["netsim"] += 1
        out.append([name, key, real_encode(msg, 0, seq["netsim"])])

    def on_tick(k, frames):
        if k >= side_ticks:
            return
        t = k * sc.clock.dt
        netsim(M.Clock(k, t, sc.clock.mode, sc.clock.dt, sc.clock.speed), "clock")
        truth = sim.truth()
        for a in sorted(frames):
            netsim(frames[a], "sensors")
            netsim(M.Truth(k, t, truth[a]), "truth")
        for a, node in sorted(nodes.items()):
            handled[a] += 1
            if node.model.state_dim > 0:
                e = estimate_of(node)
                nis = np.array(e.nis, float).reshape(-1, 2) if e.nis else None
                targets = [M.TargetEstimateMsg(o, m, P) for o, m, P in e.targets]
                est = M.EstimateMsg(e.k, node.algorithm, e.mean, e.cov, nis, targets)
                out.append([name, "estimate", real_encode(est, a, handled[a])])
            out.append([name, "done", real_encode(M.Done(node.k, handled[a], handled[a], 0), a, handled[a])])
        if k % 10 == 0:
            netsim(M.Links(k, [M.LinkMsg(**row) for row in sim.link_table()]), "links")

    wire.encode = radio
    try:
        InProcessRunner(sim, nodes).run(on_tick=on_tick)
    finally:
        wire.encode = real_encode
    return out


def refusals(n: int) -> list:
    """[frame, verdict with body, verdict of the envelope alone] for hostile inputs."""
    import test_fuzz as F

    rows, seen = [], set()

    def add(data: bytes):
        if len(data) <= 4096 or len(rows) % 100 == 0:  # a few oversize ones, not many
            if data not in seen:
                seen.add(data)
                rows.append([data, verdict(data), verdict(data, body=False)])

    for seed in range(n):
        add(F.pack(F.Gen(seed).near_valid()))
    for seed in range(n // 4):
        g = F.Gen(10**6 + seed)
        add(F.pack(g.envelope() if seed % 3 else g.value()))
    r = random.Random(7)
    for _ in range(n // 4):  # valid frames truncated, flipped, spliced
        data = bytearray(r.choice(F.VALID_FRAMES))
        for _ in range(r.randint(1, 3)):
            i = r.randrange(len(data) + 1)
            kind = r.choice(["truncate", "flip", "splice"])
            if kind == "truncate":
                del data[i:]
            elif kind == "flip" and i < len(data):
                data[i] ^= r.randrange(1, 256)
            else:
                data[i:i] = r.randbytes(r.randint(1, 8))
        add(bytes(data))
    for frame in F.VALID_FRAMES:
        add(frame)
    # What the spec's table of refusals (docs/wire.md, section 4) and tests/test_wire.py show.
    env = lambda body, t="beacon": msgpack.packb({"v": 4, "type": t, "src": 1, "seq": 1, "dst": None, "body": body},
                                                 use_bin_type=True)
    arr = lambda a, dt="<f8": {"dtype": dt, "shape": list(np.shape(a)), "data": np.asarray(a, dt).tobytes()}
    good = {"k": 1, "position": arr([0.0, 0.0]), "cov": arr(np.eye(2)), "version": {}}
    for change in [{"k": "one"}, {"k": True}, {"k": -1}, {"k": 2**40 + 1}, {"k": 1.0},
                   {"position": arr([0.0, math.nan])}, {"position": arr([0.0, math.inf])},
                   {"position": arr([0.0, 2e12])}, {"position": arr(np.eye(2))}, {"position": arr([0.0, 0.0], "<f4")},
                   {"position": {"dtype": "<f8", "shape": [3], "data": b"\0" * 16}},
                   {"position": {"dtype": "<f8", "shape": [2**63], "data": b""}},
                   {"position": {"dtype": "<f8", "shape": [5000], "data": b"\0" * 40000}},
                   {"position": {"dtype": "<f8", "shape": [2], "data": b"\0" * 16, "x": 1}},
                   {"position": {"dtype": "<f8", "shape": [True, 1], "data": b"\0" * 8}},
                   {"position": {"dtype": "<f8", "shape": [2.0], "data": b"\0" * 16}},
                   {"position": {"dtype": "<f8", "shape": [2], "data": "x" * 16}},
                   {"cov": arr(np.ones((2, 3)))}, {"cov": arr(np.ones((64, 65)))},
                   {"version": {3: 0}}, {"version": {"3": 1}}, {"version": {-1: 1}}, {"version": [1]},
                   {"extra": 1}, {"cov": None}]:
        add(env({**good, **change}))
    for drop in good:
        add(env({f: v for f, v in good.items() if f != drop}))
    for header in [{"v": 1}, {"v": True}, {"v": 4.0}, {"src": -1}, {"src": 2**31}, {"seq": -1}, {"seq": 2**63},
                   {"dst": -1}, {"dst": "x"}, {"type": "sensor"}, {"type": 4}, {"x": 0}]:
        tree = {"v": 4, "type": "beacon", "src": 1, "seq": 1, "dst": None, "body": good, **header}
        add(msgpack.packb(tree, use_bin_type=True))
    return rows


def main() -> None:
    frames = []
    for name, (algorithm, make, side) in CASES.items():
        got = record_case(name, algorithm, make(), side)
        print(f"{name}: {len(got)} frames", file=sys.stderr)
        frames += got
    frames = [[case, key, data, canon(wire.decode(data))] for case, key, data in frames]
    for name, msg in __import__("test_fuzz").SAMPLES.items():  # every type, also those no run sends
        data = wire.encode(msg, 1, 1, 2 if name == "radio.nack" else None)
        frames.append(["samples", name, data, canon(wire.decode(data))])
    rows = refusals(4000)
    print(f"{len(frames)} frames, {len(rows)} refusal inputs "
          f"({sum(r[1][0] == 'err' for r in rows)} refused)", file=sys.stderr)
    blob = msgpack.packb({"recorded_with": "hand-written schema layer (1cc5259 and time.*)", "frames": frames,
                          "refusals": rows}, use_bin_type=True)
    OUT.write_bytes(gzip.compress(blob, 9, mtime=0))
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes)", file=sys.stderr)


if __name__ == "__main__":
    main()
