"""Flight controllers in the loop: two companion computers, each a Linux network namespace
(tests/test_netns.py's bridge, claimed under its lock) holding a `swarmloc agent --config`
process and, on its loopback, a simulated PX4 (tests/fake_fc.py's SimulatedAutopilot as a
process). The agents are Zenoh peers over the bridge; each drives its FC over MAVLink.

Two closed-loop ground robots (EKF-CI) on one circle, vehicle 2 half a radian behind vehicle 1:
vehicle 1 has GPS, vehicle 2 none, and a camera on vehicle 2 (this test, reading both
simulated vehicles' truth) sights vehicle 1 twenty times a second on a measurements key. Each
agent sends its FC the swarm's estimate at 30 Hz (ODOMETRY) and its commands as setpoints;
each FC flies them in offboard through its vehicle model and says, by PX4 EKF2's rules,
whether it fuses the odometry. The loop closes through the swarm: vehicle 2 knows where it is
only through vehicle 1's estimate and the camera. The same run without the camera is the
control: vehicle 2 then has only its model and attitude, and it strays.

Needs root (network namespaces) and a spare core (conftest.require_spare_cores); skipped otherwise,
with the reason."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml
import zenoh
from conftest import require_spare_cores
from fake_fc import ORIGIN
from test_netns import PORT, WARM_START, lan, pytestmark, wait_for_port  # noqa: F401  (lan: the fixture; pytestmark: slow, root)

from swarmloc import wire
from swarmloc.wire.messages import RelPosMsg, Sensors, VehicleMsg

RADIUS, PERIOD, TICK = 3.0, 40.0, 0.05
PHASE = {1: 0.0, 2: -0.5}  # rad: vehicle 2 trails vehicle 1 by 1.5 m along the circle
GPS = {1: True, 2: False}
DURATION = 30.0  # s after the swarm clock's epoch
SETTLE = 8.0  # s: the vehicles start at rest on a circle the reference already runs along
START_MARGIN = 4.0  # s from writing the configurations to the epoch: the FCs go offboard on holds meanwhile
CAMERA_STD = 0.03  # m
FC_PORT = 14550
TRACKING_BOUND = 0.25
"""m: most a vehicle may stray from its reference once settled, and most the two's distance may
differ from the reference's: five times the GPS's 5 cm, and ten times the camera's 3 cm."""


def reference(aid: int, t: np.ndarray) -> np.ndarray:
    a = PHASE[aid] + 2 * math.pi / PERIOD * t
    return np.c_[RADIUS * np.cos(a), RADIUS * np.sin(a)]


def config(net, aid: int, epoch: float) -> dict:
    x0 = reference(aid, np.zeros(1))[0]
    return {"version": 1, "id": aid, "swarm": "fcloop", "estimator": {"name": "ekf-ci"}, "model": "ground-robot",
            "prior": {"position": [*x0.tolist(), 0.0], "heading": PHASE[aid] + math.pi / 2, "std": 0.05,
                      "heading_std": 0.02},
            "zenoh": {"mode": "peer", "listen": [net.endpoint(aid)], "connect": [net.endpoint(1)] if aid == 2 else []},
            "sensors": [{"kind": "mavlink", "url": f"udpin:127.0.0.1:{FC_PORT}", "tick": TICK, "origin": list(ORIGIN)},
                        *([{"kind": "zenoh", "key": "drivers/camera/2", "role": "measurements"}] if aid == 2 else [])],
            "outputs": {"mavlink": {"rate_hz": 30}, "setpoints": {"enabled": True}, "log": f"est-{aid}.jsonl"},
            "clock": {"epoch": epoch},
            # The FC flies setpoints, not the model's forces: the process noise covers the difference.
            "vehicle": {"reference": {"center": [0.0, 0.0, 0.0], "radius": RADIUS, "period": PERIOD,
                                      "phase": PHASE[aid]},
                        "roster": [{"id": 3 - aid, "model": "ground-robot"}], "force_noise": 0.3,
                        "moment_noise": 3e-3}}


class Camera:
    """Vehicle 2's camera: vehicle 1's position in vehicle 2's body frame (x forward, y left),
    from both FCs' truth files, with CAMERA_STD noise, 20 times a second on agent 2's
    measurements key."""

    def __init__(self, session, truth: dict[int, Path]):
        self.pub = session.declare_publisher("drivers/camera/2", **wire.publisher_options(zenoh))
        self.truth, self.stop, self.sent = truth, threading.Event(), 0
        self.rng = np.random.default_rng(2)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _last(self, path: Path):
        lines = path.read_text().splitlines() if path.exists() else []
        return json.loads(lines[-1]) if lines else None  # (t, east, north, up, yaw, offboard, unix)

    def _run(self):
        while not self.stop.wait(0.05):
            one, two = self._last(self.truth[1]), self._last(self.truth[2])
            if one is None or two is None:
                continue
            d = np.array(one[1:4]) - np.array(two[1:4])
            c, s = math.cos(two[4]), math.sin(two[4])
            z = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]]) + CAMERA_STD * self.rng.standard_normal(3)
            msg = VehicleMsg(0.0, np.zeros(2), np.zeros(1), 1.0, [RelPosMsg(1, z, CAMERA_STD)])
            self.pub.put(wire.encode(Sensors(0, 0.0, None, [], vehicle=msg), 99, self.sent))
            self.sent += 1


def run_loop(lan, tmp_path, camera_on: bool):  # noqa: F811
    """The two companions and their FCs for DURATION s: each FC's report, each agent's stats,
    both vehicles' truth rows, the epoch."""
    # What is asserted is real time: 30 Hz at each FC, never 400 ms without a fusion, setpoints
    # flown as they come. Two agents, two simulated PX4s and the camera keep that only with CPU
    # to spare (both tests passed with 0.7 cores to spare; niced beside a load of 10 the agents
    # sent 16-23 Hz and EKF2 stopped fusing for a second): a claim about spare CPU, not the
    # protocol, so measured first and skipped with the reason if absent.
    require_spare_cores(1.0, "two agents and two simulated PX4s at 30 Hz in real time need a core to spare")
    net = lan([1, 2])
    root = Path(__file__).parent.parent
    procs, logs, fcs = {}, {}, {}
    for a in (1, 2):
        logs[a] = tmp_path / f"agent-{a}.log"
        procs[a] = net.popen(a, [sys.executable, "-c", WARM_START, str(tmp_path / f"agent-{a}.yaml")],
                             stdout=subprocess.DEVNULL, stderr=open(logs[a], "w"), cwd=root)
    end = time.monotonic() + 60
    while not all("warm" in logs[a].read_text() for a in (1, 2)):
        assert time.monotonic() < end and all(p.poll() is None for p in procs.values()), \
            {a: logs[a].read_text()[-2000:] for a in (1, 2)}
        time.sleep(0.05)
    epoch = time.time() + START_MARGIN
    truth = {a: tmp_path / f"truth-{a}.jsonl" for a in (1, 2)}
    for a in (1, 2):
        x0 = reference(a, np.zeros(1))[0]
        fcs[a] = net.popen(a, [sys.executable, str(root / "tests" / "fake_fc.py"), "--port", str(FC_PORT),
                               "--vehicle", "rover", "--start", *map(str, [*x0, 0.0, PHASE[a] + math.pi / 2]),
                               *(["--gps"] if GPS[a] else []), "--seed", str(a), "--ev-delay", "0.02",
                               "--truth", str(truth[a]), "--report", str(tmp_path / f"fc-{a}.json"),
                               "--epoch", str(epoch + 1.0)], stdout=subprocess.DEVNULL,
                           stderr=open(tmp_path / f"fc-{a}.log", "w"), cwd=root)
        tmp = tmp_path / f"agent-{a}.yaml.tmp"
        tmp.write_text(yaml.safe_dump(config(net, a, epoch)))
        tmp.rename(tmp_path / f"agent-{a}.yaml")
    # A client of one peer reaches both (as `swarmloc status` does), once it listens.
    wait_for_port(net.addr(2), PORT)
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", [], [net.endpoint(2)])))
    camera = Camera(session, truth)
    if camera_on:
        camera.thread.start()
    try:
        time.sleep(max(0.0, epoch + DURATION - time.time()))
        running = {a: p.poll() is None for a, p in procs.items()}
        stats = {}
        for a in (1, 2):
            for reply in session.get(f"swarmloc/fcloop/agent/{a}/stats", timeout=2.0):
                if reply.ok is not None:
                    stats[a] = wire.decode(reply.ok.payload.to_bytes()).body.data
    finally:
        camera.stop.set()
        for p in [*procs.values(), *fcs.values()]:
            p.send_signal(signal.SIGTERM)
        codes = {a: p.wait(10) for a, p in procs.items()}
        for p in fcs.values():
            p.wait(10)
        session.close()
    text = {a: logs[a].read_text() for a in (1, 2)}
    assert all(running.values()) and set(codes.values()) <= {0, 143}, {a: t[-2000:] for a, t in text.items()}
    assert all("Traceback" not in t for t in text.values()), text
    reports = {a: json.loads((tmp_path / f"fc-{a}.json").read_text()) for a in (1, 2)}
    for a in (1, 2):  # the estimate's own uncertainty at the end, from its log (outputs.log)
        last = json.loads((tmp_path / f"est-{a}.jsonl").read_text().splitlines()[-1])
        stats[a]["position_var_end"] = float(np.trace(np.array(last["cov"])[:2, :2]) / 2)
    rows = {a: np.array([json.loads(line) for line in truth[a].read_text().splitlines()]) for a in (1, 2)}
    return reports, stats, rows, epoch


def tracking(rows, epoch):
    """Once settled: each vehicle's distance from its reference, and how far the two's distance
    is from the reference's."""
    t = {a: rows[a][:, 6] - epoch for a in (1, 2)}
    errors = {}
    for a in (1, 2):
        keep = (t[a] > SETTLE) & (t[a] < DURATION)
        errors[a] = np.linalg.norm(rows[a][keep, 1:3] - reference(a, t[a][keep]), axis=1)
    span = np.linspace(SETTLE, DURATION - 0.5, 200)
    where = {a: np.c_[np.interp(span, t[a], rows[a][:, 1]), np.interp(span, t[a], rows[a][:, 2])] for a in (1, 2)}
    gap = np.linalg.norm(where[1] - where[2], axis=1) - 2 * RADIUS * math.sin(0.25)
    return errors, gap


def check_the_fcs_accept_and_fly(reports, stats):
    for a in (1, 2):
        report = reports[a]
        ev, sp = report["ev"], report["setpoints"]
        print(f"\nFC {a}: {ev['messages']} ODOMETRY from 1 s after the epoch at {ev['rate_hz']:.1f} Hz, interval p50 "
              f"{ev['interval_ms_p50']:.1f} ms p99 {ev['interval_ms_p99']:.1f} ms max {ev['interval_ms_max']:.1f} ms; "
              f"age p50 {ev['age_ms_p50']:.1f} ms p99 {ev['age_ms_p99']:.1f} ms; verdicts {ev['counts']}; "
              f"longest without a fusion {ev['fusion_gap_ms_max']:.1f} ms; setpoints {sp}; failsafes "
              f"{report['failsafes']}")
        # Accepted for the whole run (from its first second, when fusion starts): never refused
        # by the innovation gate, never too old for the fusion horizon, never so slow that
        # fusion stops; a message that arrives within one filter period of the one before is
        # dropped ("too fast", as PX4 drops it) and counted, which costs one sample, not fusion.
        refused = {"gated", "beyond-horizon", "stopped", "not-started", "unsupported-frame", "not-vision", "no-position"}
        assert not refused & set(ev["counts"]) and ev["counts"].get("fused", 0) > 0.95 * ev["messages"], ev
        assert ev["fusion_gap_ms_max"] < 2 * 200.0, ev  # EKF2 stops after 2 EV_MAX_INTERVAL without one
        assert report["offboard"] and report["failsafes"] == 0 and sp["rejected"] == 0, report
        o = stats[a]["outputs"]
        assert o["setpoints"]["track"] > 0 and not o["setpoints"]["holding"], o
        # One machine, one clock: each agent's estimate of the other's offset is within the bound.
        clocks = stats[a]["clock_offset_ms"]
        offset = (clocks.get(3 - a) or clocks[str(3 - a)])["offset_ms"]
        assert abs(offset) < 10.0 and stats[a]["clock_exceeded"] == 0, stats[a]


def summary(errors, gap, stats) -> str:
    std = math.sqrt(stats[2]["position_var_end"]) if "position_var_end" in stats[2] else float("nan")
    return (f"tracking error after {SETTLE:g} s: vehicle 1 median {np.median(errors[1]):.3f} max "
            f"{errors[1].max():.3f} m, vehicle 2 median {np.median(errors[2]):.3f} max {errors[2].max():.3f} m; "
            f"distance error max {np.abs(gap).max():.3f} m; camera sightings fused by vehicle 2: "
            f"{stats[2]['relpos_updates']}; its position std at the end {std:.3f} m")


def test_two_vehicles_hold_formation_through_the_swarm_with_their_flight_controllers_in_the_loop(lan, tmp_path):  # noqa: F811
    reports, stats, rows, epoch = run_loop(lan, tmp_path, camera_on=True)
    check_the_fcs_accept_and_fly(reports, stats)
    errors, gap = tracking(rows, epoch)
    print(summary(errors, gap, stats))
    assert errors[1].max() < TRACKING_BOUND and errors[2].max() < TRACKING_BOUND, (errors[1].max(), errors[2].max())
    assert np.abs(gap).max() < TRACKING_BOUND
    assert stats[2]["relpos_updates"] > 0.5 * DURATION / TICK and stats[2]["gps_updates"] == 0
    assert stats[2]["position_var_end"] < 0.1**2  # the camera keeps vehicle 2's estimate within centimetres


def test_without_the_camera_vehicle_2_has_only_its_model(lan, tmp_path):  # noqa: F811
    """The control: the same run, no sightings. The FCs still accept and fly everything, vehicle 1
    still tracks on its GPS; vehicle 2's estimate has nothing but its model under the commands
    and the FC's yaw, so its uncertainty grows without bound (its position std past 0.1 m in
    30 s, four or more times the camera run's) and its error with it."""
    reports, stats, rows, epoch = run_loop(lan, tmp_path, camera_on=False)
    check_the_fcs_accept_and_fly(reports, stats)
    errors, gap = tracking(rows, epoch)
    print(summary(errors, gap, stats))
    assert stats[2]["relpos_updates"] == 0
    assert errors[1].max() < TRACKING_BOUND
    assert stats[2]["position_var_end"] > 0.1**2
    assert np.median(errors[2]) > np.median(errors[1])
