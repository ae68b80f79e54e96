"""`swarmloc install-service`: the unit it writes, and that the unit's command line is an agent
that systemd can stop with SIGTERM and restart after a crash (it resumes from its checkpoint).
No systemd here: the test plays it, running ExecStart itself."""

import configparser
import os
import pwd
import queue
import shlex
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
import zenoh
from conftest import free_port

from swarmloc import wire
from swarmloc.wire.messages import EstimateMsg, OdometryMsg, Reply, Sensors

AGENT = 5
PRIOR = [1.0, 2.0]
SPEED, DT = 2.0, 0.1  # m/s east, s a tick: 0.2 m a tick


def swarmloc(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=60, cwd=cwd)


def write_config(tmp_path, **changes):
    data = {"version": 1, "id": AGENT, "swarm": f"svc{os.getpid()}", "estimator": {"name": "il"},
            "model": "planar-speed-heading", "prior": {"position": PRIOR, "std": 0.5},
            "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]}, "state_dir": "state", **changes}
    path = tmp_path / "agent.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def parse_unit(text: str) -> configparser.ConfigParser:
    unit = configparser.ConfigParser(interpolation=None)  # systemd's % specifiers are not configparser's
    unit.optionxform = str
    unit.read_string(text)
    return unit


def me() -> str:
    return pwd.getpwuid(os.getuid()).pw_name


def test_the_unit_file(tmp_path):
    config = write_config(tmp_path)
    units = tmp_path / "units"
    p = swarmloc("install-service", "--config", "agent.yaml", "--unit-dir", str(units), "--user", me(), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    path = units / f"swarmloc-agent-{AGENT}.service"
    text = path.read_text()
    unit = parse_unit(text)
    s = unit["Service"]
    argv = shlex.split(s["ExecStart"])
    assert argv == [sys.executable, "-P", "-m", "agents", "agent", "--config", str(config)]  # absolute, from a relative one
    assert os.path.isfile(argv[0]) and os.access(argv[0], os.X_OK)
    # The interpreter is the only environment-specific path: no other venv or python is named.
    rest = text.replace(sys.executable, "")
    assert ".venv" not in rest and "bin/python" not in rest
    assert s["WorkingDirectory"] == str(tmp_path) and s["User"] == me()
    assert (s["Restart"], s["RestartSec"], s["KillSignal"], s["TimeoutStopSec"]) == ("on-failure", "2", "SIGTERM", "5")
    assert s["SuccessExitStatus"] == "143" and s["RestartPreventExitStatus"] == "2"
    assert (s["StandardOutput"], s["StandardError"]) == ("journal", "journal")
    assert unit["Install"]["WantedBy"] == "multi-user.target"
    assert path.stat().st_mode & 0o777 == 0o644
    state = tmp_path / "state"
    assert state.is_dir() and state.stat().st_mode & 0o777 == 0o700 and state.stat().st_uid == os.getuid()
    assert f"systemctl daemon-reload && systemctl enable --now {path.name}" in p.stdout
    assert f"journalctl -u {path.name}" in p.stdout
    # A second install replaces the unit (same text) and leaves the state directory alone.
    again = swarmloc("install-service", "--config", str(config), "--unit-dir", str(units), "--user", me())
    assert again.returncode == 0 and again.stdout.startswith(f"replaced {path}") and path.read_text() == text


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_systemd_reads_every_line(tmp_path):
    """systemd's own parser, offline: it names an unknown key or value on stderr (and still exits 0)."""
    units = tmp_path / "units"
    assert swarmloc("install-service", "--config", str(write_config(tmp_path)), "--unit-dir", str(units)).returncode == 0
    p = subprocess.run(["systemd-analyze", "verify", str(units / f"swarmloc-agent-{AGENT}.service")],
                       capture_output=True, text=True, timeout=30)
    assert p.returncode == 0 and p.stderr == "", p.stderr


def test_a_user_unit(tmp_path):
    units = tmp_path / ".config" / "systemd" / "user"
    p = swarmloc("install-service", "--config", str(write_config(tmp_path)), "--unit-dir", str(units),
                 "--name", "field-5")
    assert p.returncode == 0, p.stderr
    assert parse_unit((units / "field-5.service").read_text())["Install"]["WantedBy"] == "default.target"
    assert "systemctl --user daemon-reload && systemctl --user enable --now field-5.service" in p.stdout
    assert "journalctl --user -u field-5.service" in p.stdout


def test_a_path_with_blanks_stays_one_word(tmp_path):
    (tmp_path / "field kit").mkdir()
    config = write_config(tmp_path / "field kit")
    p = swarmloc("install-service", "--config", str(config), "--dry-run")
    assert p.returncode == 0, p.stderr
    s = parse_unit(p.stdout)["Service"]
    assert shlex.split(s["ExecStart"])[-1] == str(config) and s["WorkingDirectory"] == str(config.parent)


def test_dry_run_writes_nothing(tmp_path):
    config = write_config(tmp_path)
    units = tmp_path / "units"
    p = swarmloc("install-service", "--config", str(config), "--unit-dir", str(units), "--dry-run")
    assert p.returncode == 0, p.stderr
    assert not units.exists() and not (tmp_path / "state").exists()
    assert parse_unit(p.stdout)["Service"]["Restart"] == "on-failure"
    assert swarmloc("install-service", "--config", str(config), "--unit-dir", str(units)).returncode == 0
    assert (units / f"swarmloc-agent-{AGENT}.service").read_text() == p.stdout


@pytest.mark.parametrize("config, args, says", [
    ({"prior": {"position": [1, 2, 3]}}, [], "error: {config}: prior.position: 3 numbers; model planar-speed-heading"),
    ({"estimator": {"name": "csl-ctl"}}, [], "error: {config}: estimator.name: csl-ctl needs every agent's prior"),
    ({}, ["--name", "a/b"], "error: 'a/b' is not a systemd unit name"),
    ({}, ["--user", "no-such-user-here"], "error: no such user 'no-such-user-here'"),
    ({}, ["--user", "root", "--unit-dir", "{tmp}/.config/systemd/user"], "error: --user is for a system unit"),
], ids=["config", "estimator", "name", "user", "user-unit"])
def test_refused_is_exit_2_and_writes_nothing(tmp_path, config, args, says):
    path = write_config(tmp_path, **config)
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    if "--unit-dir" not in args:
        args += ["--unit-dir", str(tmp_path / "units")]
    p = swarmloc("install-service", "--config", str(path), *args)
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.startswith(says.format(config=path)), p.stderr
    assert "Traceback" not in p.stderr
    assert sorted(f.name for f in tmp_path.iterdir()) == ["agent.yaml"]


class Driver:
    """What surrounds the agent on a companion computer: the sensor driver publishing its frames,
    a peer listening to its estimates. One Zenoh peer session, which the agent connects to
    (so it outlives every restart), on 127.0.0.1."""

    def __init__(self, swarm: str):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.keys = wire.Keys(swarm)
        self.session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", listen=[self.endpoint])))
        self.estimates, self.alive = queue.SimpleQueue(), queue.SimpleQueue()
        self.subs = [
            self.session.declare_subscriber(self.keys.estimate(AGENT), lambda s: self.estimates.put(
                wire.decode(s.payload.to_bytes(), expect=(EstimateMsg,)).body)),
            self.session.liveliness().declare_subscriber(self.keys.alive(AGENT), lambda s: self.alive.put(s.kind),
                                                         history=True),
        ]
        self.sensors = self.session.declare_publisher(self.keys.sensors(AGENT), **wire.publisher_options(zenoh))

    def wait_alive(self):
        deadline = time.monotonic() + 30
        while self.alive.get(timeout=max(0.0, deadline - time.monotonic())) != zenoh.SampleKind.PUT:
            pass

    def tick(self, k: int) -> EstimateMsg:
        """Tick k's sensor frame (odometry only: east at SPEED), and the estimate it brings."""
        odometry = OdometryMsg(dt=DT, speed=SPEED, heading=0.0, speed_std=0.05, heading_std=0.01)
        self.sensors.put(wire.encode(Sensors(k, k * DT, odometry, []), 0, k + 1))
        deadline = time.monotonic() + 10
        while (e := self.estimates.get(timeout=max(0.0, deadline - time.monotonic()))).k != k:
            pass
        return e

    def ticks(self, ks) -> EstimateMsg:
        *head, last = ks
        for k in head:
            self.tick(k)
        time.sleep(0.25)  # the daemon checkpoints at most every 0.2 s: let the last tick be checkpointed
        return self.tick(last)

    def close(self):
        self.session.close()


def stats(endpoint: str, swarm: str) -> dict:
    """An agent's health, as a monitoring client gets it: a Zenoh client of the agent's own
    listen endpoint, querying agent/<id>/stats (docs/wire.md section 8)."""
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
    try:
        (reply,) = [r for r in session.get(wire.Keys(swarm).stats(AGENT), timeout=5.0) if r.ok is not None]
        body = wire.decode(reply.ok.payload.to_bytes(), expect=(Reply,)).body
        assert body.ok
        return body.data
    finally:
        session.close()


def checkpoint(state_dir):
    flat = np.load(state_dir / f"agent-{AGENT}.state.npy")
    return int(flat[0]), flat[1:3]


@pytest.mark.slow
def test_the_units_command_runs_stops_and_resumes(tmp_path):
    swarm = f"svc{os.getpid()}"
    driver = Driver(swarm)
    listen = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(tmp_path, swarm=swarm, zenoh={"mode": "peer", "listen": [listen], "connect": [driver.endpoint]})
    p = swarmloc("install-service", "--config", str(config), "--dry-run")
    assert p.returncode == 0, p.stderr
    service = parse_unit(p.stdout)["Service"]
    argv, cwd = shlex.split(service["ExecStart"]), service["WorkingDirectory"]
    state = tmp_path / "state"
    procs = []

    def start():  # what systemd does at boot, and again RestartSec after a failure
        procs.append(subprocess.Popen(argv, cwd=cwd, stderr=subprocess.PIPE, text=True))
        driver.wait_alive()
        return procs[-1]

    try:
        agent = start()
        first = driver.ticks(range(5))
        assert first.algorithm == "il" and np.allclose(first.mean, [PRIOR[0] + 5 * SPEED * DT, PRIOR[1]])
        health = stats(listen, swarm)
        assert (health["id"], health["algorithm"], health["k"], health["ticks"]) == (AGENT, "il", 4, 5)
        assert health["rejected"] == {} and health["ticks_skipped"] == 0

        # systemctl stop: SIGTERM, and the agent is gone well inside TimeoutStopSec.
        t0 = time.monotonic()
        agent.send_signal(signal.SIGTERM)
        assert agent.wait(timeout=2) == 143 and time.monotonic() - t0 < 2
        assert checkpoint(state)[0] == 4

        agent = start()
        before = driver.ticks(range(5, 10))
        assert before.k == 9 and np.allclose(before.mean, [PRIOR[0] + 10 * SPEED * DT, PRIOR[1]])  # no tick lost
        k, mean = checkpoint(state)
        assert k == 9 and np.array_equal(mean, before.mean)

        # A crash: Restart=on-failure starts the same command again, which resumes from state_dir.
        agent.kill()
        agent.wait(timeout=5)
        agent = start()
        after = driver.tick(10)
        assert np.allclose(after.mean, before.mean + [SPEED * DT, 0.0])  # from tick 9, not from the prior
        assert np.all(np.diag(after.cov) >= np.diag(before.cov))
        assert stats(listen, swarm)["k"] == 10
        agent.terminate()
        assert agent.wait(timeout=2) == 143
        log = agent.stderr.read()
        assert f"agent {AGENT} resumed from its checkpoint of tick 9" in log
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        driver.close()
