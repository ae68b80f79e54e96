"""python -m netsim: the network emulator process (normally started by `swarmloc run`)."""

from __future__ import annotations

from swarmloc.process import exit_on_sigterm, pin_blas

pin_blas()  # before numpy loads


import argparse
import json
import logging
import sys
from pathlib import Path

from netsim import tune_gc
from netsim.server import NetsimServer, ServerConfig, SetupError
from swarmloc.experiment import scenario as scenarios
from swarmloc.wire.auth import Keyring


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m netsim", description=__doc__)
    p.add_argument("scenario", help="built-in scenario name or YAML path")
    p.add_argument("--swarm", default="default")
    p.add_argument("--listen", action="append", default=None, help="Zenoh endpoint (repeatable)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--await-rejoin", action="store_true",
                   help="lockstep: when an agent's process goes away (not a kill fault), wait for it to come back "
                        "before the next tick (its launcher restarts crashed agents)")
    p.add_argument("--join-timeout", type=float, default=30.0)
    p.add_argument("--tick-timeout", type=float, default=10.0)
    p.add_argument("--keys", type=Path, default=None, help="the swarm's key file: every frame sealed and opened with it")
    p.add_argument("--record", type=Path, default=None, help="write the MCAP recording here (default: OUT/run.mcap)")
    p.add_argument("--no-record", action="store_true", help="no run.mcap")
    p.add_argument("--view", type=int, default=None, metavar="PORT",
                   help="serve the live view over the Foxglove WebSocket protocol on 127.0.0.1:PORT (0: a free port)")
    p.add_argument("--ros2-domain", type=int, default=None, help="publish every estimate on ROS 2 topics of this "
                   "ROS_DOMAIN_ID over rmw_zenoh's keys (docs/ros2.md)")
    p.add_argument("--ros2-namespace", default="/swarmloc")
    p.add_argument("--ros2-distro", default="jazzy", choices=("jazzy", "humble"))
    p.add_argument("-v", "--verbose", action="store_true")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format="%(asctime)s netsim %(levelname)s %(message)s")
    try:
        sc = scenarios.load(a.scenario)
        if a.seed is not None:
            sc = sc.with_overrides(seed=a.seed)
        keyring = None if a.keys is None else Keyring.load(a.keys)
        topics = None
        if a.ros2_domain is not None:
            from swarmloc.wire.ros2 import Topics

            topics = Topics(a.ros2_domain, a.ros2_namespace, a.ros2_distro)
    except (scenarios.ScenarioError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    exit_on_sigterm()
    tune_gc()
    cfg = ServerConfig(swarm=a.swarm, listen=tuple(a.listen or ["tcp/127.0.0.1:7447"]), out=a.out,
                       join_timeout=a.join_timeout, tick_timeout=a.tick_timeout, plots=not a.no_plots,
                       await_rejoin=a.await_rejoin, keyring=keyring, keys_path=a.keys, view_port=a.view, ros2=topics,
                       record=None if a.no_record else a.record or (a.out / "run.mcap" if a.out is not None else None))
    try:
        m = NetsimServer(sc, cfg).run()
    except scenarios.ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except SetupError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        return 130
    if a.out is None:
        print(json.dumps(m, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
