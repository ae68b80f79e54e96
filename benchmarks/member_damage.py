"""How far one member can move the others' estimates with lies that pass every plausibility
check (issue 26, finding 7; docs/security.md, "A member's damage (finding 7)").

In process, lockstep wang2019 (seed 7, 100 s): every range start agent 2 sends has its range
SIZE m longer, plain ("range": refused once beyond the bound) or with its noise inflated to
(SIZE/3)^2 so that it stays within 3 sigma and passes every check ("scale"). Prints, per size,
the largest and mean position shift of agents 1, 3 and 4 from the unattacked run, and the
refusals counted.

usage: python benchmarks/member_damage.py
"""

import msgspec
import numpy as np

from swarmloc.estimators import make_nodes
from swarmloc.experiment import scenario as S
from swarmloc.experiment.runner import InProcessRunner
from swarmloc.wire.messages import DclStart
from netsim.sim import Simulation

LIAR = 2


def run(sc, lie: str | None, size: float):
    nodes = make_nodes("ukf-dcl", sc)
    node = nodes[LIAR]

    def lying(f):
        def wrapped(*a, **kw):
            out = f(*a, **kw)
            for i, s in enumerate(out):
                m = getattr(s, "msg", None)
                if isinstance(m, DclStart) and m.key[1] == 0:
                    z, R = m.z.copy(), m.R.copy()
                    z[0] += size
                    if lie == "scale":
                        R[0, 0] = max(R[0, 0], (size / 3.0) ** 2)
                    out[i] = msgspec.structs.replace(s, msg=msgspec.structs.replace(m, z=z, R=R)) \
                        if isinstance(s, msgspec.Struct) else type(s)(msgspec.structs.replace(m, z=z, R=R), s.dst)
            return out
        return wrapped

    if lie is not None:
        node.step, node.receive = lying(node.step), lying(node.receive)
    record = InProcessRunner(Simulation(sc), nodes).run()
    drops = sum(n for a, nd in nodes.items() for r, n in nd.drops.items() if r.startswith("implausible"))
    return record.trace("ukf-dcl"), drops


def main() -> None:
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 100.0})
    ref, _ = run(sc, None, 0.0)
    others = [i for i, a in enumerate(sc.agent_ids) if a != LIAR]
    print("lie    size_m  max_shift_m  mean_shift_m  refused")
    for lie in ("range", "scale"):
        for size in (5.0, 20.0, 50.0, 100.0, 300.0, 1000.0):
            tr, drops = run(sc, lie, size)
            shift = np.linalg.norm(tr.mean[:, others, :2] - ref.mean[:, others, :2], axis=-1)
            print(f"{lie:6s} {size:7.0f}  {np.nanmax(shift):11.2f}  {np.nanmean(shift):12.2f}  {drops:7d}")


if __name__ == "__main__":
    main()
