"""Benchmark: the cost of frame authentication (docs/security.md) and its share of a UKF-DCL tick.

Takes every radio frame of an in-process wang2019 UKF-DCL run (the frames the agents would
send, with their real sizes), then times, side by side in one process: sealing (the sender),
opening (netsim and the receiver each open it) and netsim's delivery tag, per frame, median of
repetitions. The share of a tick is the auth work of one tick's frames (seal + 2 opens + one
delivery tag each, as in a lockstep run over netsim) over the time the same run's ticks take
in process (the estimators' own work, no transport). Usage:
    python benchmarks/bench_auth.py [--ticks 200] [--repeat 5]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from datetime import date

from machine import cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

from netsim.sim import Simulation  # noqa: E402
from swarmloc import wire  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.runner import make_nodes  # noqa: E402
from swarmloc.node import Outbox  # noqa: E402
from swarmloc.wire import auth


def frames_of_a_run(ticks: int) -> tuple[list[bytes], float]:
    """Every radio frame of a wang2019 UKF-DCL run of `ticks` ticks (delivered at once, in
    order, as a perfect radio would), and the run's wall time per tick."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": ticks * 0.5})
    nodes = make_nodes("ukf-dcl", sc)
    sim = Simulation(sc)
    outboxes = {a: Outbox(a) for a in nodes}
    frames: list[bytes] = []
    start = time.perf_counter()
    for _ in range(sc.clock.steps + 1):
        _, _, sensed = sim.tick()
        queue = [(a, s) for a in nodes for s in nodes[a].step(sensed[a])]
        while queue:
            a, send = queue.pop(0)
            if not hasattr(send, "msg"):
                continue  # a timer: lockstep fires none within a tick
            tx = outboxes[a].encode(send)
            if tx is None:
                continue  # over its type's frame limit: never sent
            frames.append(tx.data)
            msg = wire.decode(tx.data).body
            for b in ([send.dst] if send.dst is not None else [x for x in nodes if x != a]):
                queue += [(b, s) for s in nodes[b].receive(a, msg)]
    return frames, (time.perf_counter() - start) / (sc.clock.steps + 1)


def per_frame(fn, items, repeat: int) -> float:
    """Median over `repeat` passes of the mean µs per item."""
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for x in items:
            fn(x)
        runs.append((time.perf_counter() - t0) / len(items) * 1e6)
    return statistics.median(runs)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ticks", type=int, default=200)
    p.add_argument("--repeat", type=int, default=5)
    a = p.parse_args()
    frames, tick_s = frames_of_a_run(a.ticks)
    # Per-member identity (issue 26): agent 1 seals with its own MAC key for netsim, netsim opens
    # it with that key (derived from the hub's) and tags each delivery under the receiver's key;
    # the receiver checks that tag. netsim's broadcasts (the clock, once a tick) are signed.
    hub = auth.Keyring.generate("bench", [1, 2])
    a1, a2 = hub.for_member("agent-1"), hub.for_member("agent-2")
    key = wire.Keys("bench").radio_tx(1)
    sealer = auth.Sealer(a1, 1)
    sealed = [sealer.seal(f, key, 0) for f in frames]
    att = wire.encode_delivery(1, 0.0)
    tagged = [(d, att + auth.delivery_tag(hub, 2, att, d)) for d in sealed]

    def open_all(_):
        opener = auth.Opener(hub, 0)  # a fresh window: every frame is new to it
        for d in sealed:
            opener.open(d, key)

    netsim = auth.Sealer(hub, 0)
    signed = [netsim.seal(f, key) for f in frames]

    def verify_signed(_):
        opener = auth.Opener(a2, 2)
        for d in signed:
            opener.open(d, key)

    # Per-member identity (issue 26), measured before it is built: an Ed25519 signature from
    # `cryptography` over the same bytes the HMAC covers, signed by the sender, verified by each
    # receiver; the frame carries 64 bytes of signature instead of a 16-byte tag.
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    member = Ed25519PrivateKey.generate()
    public = member.public_key()
    raw_signed = [(f, member.sign(f)) for f in frames]
    sign_us = per_frame(member.sign, frames, a.repeat)
    verify_us = per_frame(lambda fs: public.verify(fs[1], fs[0]), raw_signed, a.repeat)
    seal_sig_us = per_frame(lambda f: netsim.seal(f, key), frames, a.repeat)
    open_sig_us = per_frame(verify_signed, [None], a.repeat) / len(signed)

    seal_us = per_frame(lambda f: sealer.seal(f, key, 0), frames, a.repeat)
    open_us = per_frame(open_all, [None], a.repeat) / len(sealed)
    tag_us = per_frame(lambda d: auth.delivery_tag(hub, 2, att, d), sealed, a.repeat)
    check_us = per_frame(lambda dt: auth.check_delivery(a2, 2, dt[1], dt[0]), tagged, a.repeat)
    decode_us = per_frame(wire.decode, frames, a.repeat)
    sizes = sorted(len(f) for f in frames)
    per_tick = len(frames) / (a.ticks + 1)
    agents = 4
    auth_tick_us = per_tick * (seal_us + open_us + tag_us + check_us) + seal_sig_us + agents * open_sig_us
    print(f"# bench_auth ({date.today()}, {platform.python_version()}, {cpu_model()})")
    print(f"wang2019 UKF-DCL, {a.ticks + 1} ticks: {len(frames)} radio frames, {per_tick:.1f} a tick, "
          f"sizes median {sizes[len(sizes) // 2]} B (min {sizes[0]}, max {sizes[-1]})")
    print("| per frame | µs |")
    print("|---|---|")
    print(f"| seal, MAC under the sender's own key (S2) | {seal_us:.2f} |")
    print(f"| open at netsim (S2: receiver, key, MAC, window) | {open_us:.2f} |")
    print(f"| netsim's delivery tag (the receiver's key) | {tag_us:.2f} |")
    print(f"| the receiver's check of that tag | {check_us:.2f} |")
    print(f"| seal, netsim's signature (E2) | {seal_sig_us:.2f} |")
    print(f"| open, signature (E2: receiver, key, Ed25519 verify, window) | {open_sig_us:.2f} |")
    print(f"| wire.decode, for scale | {decode_us:.2f} |")
    print(f"| Ed25519 sign (a member's own key) | {sign_us:.2f} |")
    print(f"| Ed25519 verify | {verify_us:.2f} |")
    ed_tick_us = per_tick * (sign_us + 2 * verify_us + tag_us)
    print(f"a tick's frames: {auth_tick_us:.0f} µs of authentication (seal, open, delivery tag and its check each; "
          f"the clock signed once and verified by {agents} agents) against "
          f"{tick_s * 1e6:.0f} µs of the estimators' work a tick in process: {100 * auth_tick_us / (tick_s * 1e6):.1f} %")
    print(f"the same with Ed25519 signatures (sign + 2 verifies + 1 delivery tag each): {ed_tick_us:.0f} µs, "
          f"{100 * ed_tick_us / (tick_s * 1e6):.1f} %")


if __name__ == "__main__":
    main()
