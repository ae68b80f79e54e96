"""Issue 26, trust round two: each finding attacked again from a separate process that has only
what that attacker has (tests/attacker.py), and its outcome asserted. Outsider attacks leave a
lockstep run's estimates bit for bit those of the same run in process, every refusal counted by
reason; crash cases leave a run directory with every tick up to the crash."""

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from conftest import netsim_pid, swarm_pids
from helpers import in_process

from swarmloc.experiment import scenario as S
from swarmloc.experiment.recording import FLUSH_PERIOD

pytestmark = pytest.mark.slow
ATTACKER = Path(__file__).with_name("attacker.py")


def short(tmp_path: Path, duration: float = 100.0):
    """wang2019, shorter: the attacks need a run, not the paper's length."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": duration})
    path = tmp_path / "wang2019-short.yaml"
    path.write_text(sc.to_yaml())
    return sc, path


def attack(cli, name: str, first: int, last: int, *args, timeout: float = 200) -> dict:
    p = subprocess.run([sys.executable, str(ATTACKER), name, cli.endpoint, cli.swarm, str(first), str(last),
                        *map(str, args)], capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def attacked_run(cli, tmp_path, name: str, *args, first: int = 20, margin: int = 50, member: bool = False):
    """A short wang2019 run attacked by tests/attacker.py's `name` from tick `first` to `margin`
    ticks before its end; (scenario, run directory, the attacker's report) once it ended well.
    member: the attacker is handed the run's key directory (it takes agent 2's keys from it),
    once the run has made it."""
    sc, path = short(tmp_path)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    try:
        if member:
            cli.wait_tick(5, run, timeout=240)
            args = (out / "logs" / "keys", *args)
        report = attack(cli, name, first, sc.clock.steps - margin, *args)
    except AssertionError:
        run.kill()
        raise AssertionError(run.communicate()) from None
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    return sc, out, report


def assert_unattacked(sc, out: Path) -> dict:
    """The run's estimates are bit for bit those of the same run in process."""
    m = json.loads((out / "metrics.json").read_text())
    assert m["tick_timeouts"] == 0 and m["unresponsive_agents"] == []
    assert m["ticks"] == sc.clock.steps + 1
    zen = np.load(out / "estimates" / "ukf-dcl.npz")
    record, _, _ = in_process(sc)
    assert np.array_equal(zen["mean"], record.trace("ukf-dcl").mean)
    assert np.array_equal(zen["cov"], record.trace("ukf-dcl").cov)
    return m


def test_launcher_obeys_only_netsims_sealed_events_and_clock(cli, tmp_path):
    """Finding 1: unsealed kill and restart events, a clock on events, a `done` on clock: the
    launcher kills nobody, starts nobody, does not crash, and counts each frame by reason."""
    sc, out, report = attacked_run(cli, tmp_path, "launcher")
    assert report["rounds"] >= 10
    m = assert_unattacked(sc, out)
    assert m["agent_events"] == [] and m["crashes"] == []
    sent = Counter(report["sent"])
    got = m["launcher"]["rejected"]
    for kind in ("events", "clock"):
        expected = {r.split("/")[1]: n for r, n in sent.items() if r.startswith(kind + "/")}
        seen = dict(got.get(kind, {}))
        if kind == "clock":  # a replay is a counter seen before or one below the window
            seen["auth-replayed"] = seen.get("auth-replayed", 0) + seen.pop("auth-too-old", 0)
        assert seen == expected, kind


def test_a_long_frame_on_a_key_of_small_ones_is_refused_by_its_length(cli, tmp_path):
    """Cheap refusals first: 60 KB frames ending in netsim's real trailer on the clock key and on
    an agent's `done` key, whose types take a few hundred bytes at most (docs/wire.md, section
    4), are refused by every receiver as `oversize` before any MAC, each one counted, and the
    run's estimates are untouched."""
    sc, out, report = attacked_run(cli, tmp_path, "oversize")
    sent = Counter(report["sent"])
    assert sent["clock/oversize"] >= 50 and sent["done/oversize"] >= 50
    m = assert_unattacked(sc, out)
    assert m["launcher"]["rejected"]["clock"] == {"oversize": sent["clock/oversize"]}
    assert m["rejected"]["done"] == {"oversize": sent["done/oversize"]}
    for aid in sc.agent_ids:
        assert m["agent_stats"][str(aid)]["rejected"] == {"oversize": sent["clock/oversize"]}, aid


def test_a_member_revoked_while_the_run_goes_is_refused_from_then_on(cli, tmp_path):
    """`swarmloc keys revoke` on a running swarm's key directory: netsim reads the revocation
    within a second, agent 2 leaves the run for good (an `agent_events` entry `revoked`), every
    frame it seals afterwards with its own keys is refused (`auth-revoked`), and the others run
    on to the end with no tick timed out."""
    import shutil

    sc, path = short(tmp_path, 800.0)  # 1601 ticks: still going when the attacker is up
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    try:
        keys, stolen = out / "logs" / "keys", tmp_path / "agent-2-keys"
        cli.wait_tick(20, run, timeout=240)
        stolen.mkdir(mode=0o700)
        for name in ("agent-2.secret", "members.json"):  # what agent 2 holds
            shutil.copy2(keys / name, stolen / name)
        before = cli.wait_tick(0, run)["k"]
        p = cli.run("keys", "revoke", str(keys), "2")
        assert p.returncode == 0, p.stderr
        time.sleep(1.5)  # netsim looks at the key file once a second
        at = cli.wait_tick(0, run)["k"]
        report = attack(cli, "revoked", at + 2, sc.clock.steps - 20, stolen)
    except AssertionError:
        run.kill()
        raise AssertionError(run.communicate()) from None
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["ticks"] == sc.clock.steps + 1 and m["tick_timeouts"] == 0 and m["unresponsive_agents"] == [], stderr
    events = [e for e in m["agent_events"] if e["agent"] == 2]
    assert [e["event"] for e in events] == ["revoked"] and before <= events[0]["k"] <= at, (before, at, events)
    sent = Counter(report["sent"])
    assert sent["tx/auth-revoked"] >= 20 and sent["done/auth-revoked"] >= 20
    for kind in ("tx", "done"):
        assert m["rejected"][kind].get("auth-revoked", 0) >= sent[f"{kind}/auth-revoked"], (kind, m["rejected"])
    zen = np.load(out / "estimates" / "ukf-dcl.npz")
    others = [i for i, a in enumerate(sc.agent_ids) if a != 2]
    assert np.isfinite(zen["mean"][-1, others]).all()  # the others estimate to the end


def gone(pid: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not Path(f"/proc/{pid}").exists(), f"{pid} still running"


@pytest.mark.parametrize("how", ["netsim-kill", "launcher-kill", "launcher-term", "launcher-hup"])
def test_a_crash_keeps_every_finished_tick(cli, tmp_path, how):
    """Crash cases: kill -9 of netsim, or kill -9, SIGTERM or SIGHUP of the launcher, mid-run.
    The run directory then holds metrics.json and the estimates of every tick up to the crash,
    rebuilt from run.mcap (by the launcher, or by `swarmloc results DIR` when the launcher itself
    died), bit for bit those of the same run in process up to there; the run exits non-zero.
    The paper's length (801 ticks): on a quiet machine a shorter run ends before it is hit."""
    sc, path = short(tmp_path, 400.0)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    crash_at = cli.wait_tick(80, run, timeout=240)["k"]  # netsim is in this tick: the one before is finished
    # run.mcap is flushed at the end of a tick once FLUSH_PERIOD of wall time has passed: one more
    # tick ended after that long holds everything up to crash_at - 1 on disk.
    time.sleep(FLUSH_PERIOD * 1.5)
    cli.wait_tick(cli.wait_tick(0, run)["k"] + 1, run, timeout=60)
    victim = netsim_pid(cli.swarm) if how == "netsim-kill" else run.pid
    os.kill(victim, {"kill": signal.SIGKILL, "term": signal.SIGTERM, "hup": signal.SIGHUP}[how.split("-")[1]])
    stdout, stderr = run.communicate(timeout=180)
    assert run.returncode != 0
    if how == "launcher-kill":  # nobody left to rebuild the results: the next look at the directory does
        for pid in swarm_pids(cli.swarm):
            gone(pid)
        assert not (out / "metrics.json").exists()
        p = cli.run("results", str(out), "--no-plots", timeout=180)
        assert p.returncode == 0, p.stderr
        assert "rebuilt" in p.stdout
    else:
        assert "rebuilt from" in stderr and "ended after tick" in stderr, stderr
    m = json.loads((out / "metrics.json").read_text())
    last = m["ended_early"]["last_tick"]
    # The rebuild leaves out the last two recorded ticks (their final estimates may be missing).
    assert crash_at - 3 <= last < sc.clock.steps and m["ticks"] == last + 1
    zen = np.load(out / "estimates" / "ukf-dcl.npz")
    ref = in_process(sc)[0].trace("ukf-dcl")
    assert not np.isnan(zen["mean"]).all(axis=(1, 2)).any()  # every tick has estimates
    assert np.array_equal(zen["mean"], ref.mean[:last + 1], equal_nan=True)
    assert np.array_equal(zen["cov"], ref.cov[:last + 1], equal_nan=True)


def test_no_single_frame_locks_its_sender_out(cli, tmp_path):
    """Finding 8, one member's key (agent 2's own): frames claiming netsim with counters eleven
    days ahead carry agent 2's signature and are refused (bad-signature, finding 10); agent 2's
    own with counters that far ahead are refused (from-the-future). Nothing changes: the run is
    bit for bit the unattacked one, netsim's and agent 2's own frames still count."""
    sc, out, report = attacked_run(cli, tmp_path, "lockout", member=True)
    assert report["rounds"] >= 10
    m = assert_unattacked(sc, out)
    sent = Counter(report["sent"])
    assert m["rejected"]["tx"] == {"auth-from-the-future": sent["tx/auth-from-the-future"]}
    assert m["launcher"]["rejected"]["clock"] == {"auth-bad-signature": sent["clock/auth-bad-signature"]}
    for aid in sc.agent_ids:
        want = sent["clock/auth-bad-signature"] + sent[f"{aid}/auth-bad-signature"]
        assert m["agent_stats"][str(aid)]["rejected"] == {"auth-bad-signature": want}, aid


def test_a_replayed_delivery_at_full_rate_changes_nothing(cli, tmp_path):
    """Finding 4, outsider: one captured delivery replayed at agent 2 as fast as a process can
    publish. Copies are refused before the inbox (their number is consumed already), so no
    genuine delivery is lost and the lockstep run stays bit for bit the unattacked one."""
    sc, path = short(tmp_path)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    report = attack(cli, "flood", 20, sc.clock.steps, 20000, timeout=600)
    stdout, stderr = run.communicate(timeout=600)
    assert run.returncode == 0, stderr
    assert report["frames"] == 20000
    m = assert_unattacked(sc, out)
    st = m["agent_stats"]["2"]
    # Every copy that reached agent 2 is counted (Zenoh may drop some of a flood on the way).
    assert set(st["rejected"]) == {"rx-out-of-sequence"}
    assert report["frames"] // 2 <= st["rejected"]["rx-out-of-sequence"] <= report["frames"]
    assert st["deliveries_lost"] == 0 and st["inbox"]["dropped"] == 0


def test_a_flood_of_large_fake_frames_costs_a_mac_each_and_pushes_nothing_out(cli, tmp_path):
    """Finding 5, outsider: 60 KB frames ending in a captured trailer of netsim's, at 10,000 a
    second on agent 2's radio and sensor keys. Each is refused in Zenoh's callback (its tag is
    wrong) before it takes a place in the inbox, so no genuine frame is dropped and the lockstep
    run stays bit for bit the unattacked one; every refusal is counted by reason."""
    sc, path = short(tmp_path, duration=200.0)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    report = attack(cli, "trailer-flood", 20, sc.clock.steps - 20, 50000, 60000, 10000, timeout=600)
    stdout, stderr = run.communicate(timeout=600)
    assert run.returncode == 0, stderr
    assert report["frames"] >= 5000  # the flood overlapped enough of the run to matter
    m = json.loads((out / "metrics.json").read_text())
    st = m["agent_stats"]["2"]
    print(f"trailer flood: {report['frames']} frames at {report['rate']:.0f}/s; agent 2 refused {st['rejected']}, "
          f"inbox {st['inbox']}, deliveries lost {st['deliveries_lost']}")
    assert_unattacked(sc, out)
    # Every frame that reached agent 2 is refused for its tag. How many reach it is the
    # flooder's DROP publisher's and the machine's affair (24,105 of 50,000 on a loaded CI run,
    # 49,909 on a quiet one): at least a tenth, for the flood to have mattered.
    # On the radio key the seal is netsim's delivery tag (under agent 2's own key): bad-delivery.
    assert set(st["rejected"]) <= {"auth-bad-tag", "auth-bad-delivery"}
    assert report["frames"] // 10 <= sum(st["rejected"].values()) <= report["frames"]
    assert st["deliveries_lost"] == 0 and st["inbox"]["dropped"] == 0
    for aid in sc.agent_ids:
        if aid != 2:
            assert m["agent_stats"][str(aid)]["rejected"] == {}, aid


def test_a_member_cannot_stop_the_swarm_as_netsim(cli, tmp_path):
    """Finding 9, one member's key: one sealed `stop` on the clock, sealed as netsim, made every
    agent exit at once. With per-member identity (finding 10) agent 2's keys cannot sign as
    netsim: every agent and the launcher refuse it (bad-signature) and the run is bit for bit the
    unattacked one. (A run whose agents do stop early still exits 1 and says so: the launcher's
    check stays, for a netsim that is itself compromised.)"""
    sc, path = short(tmp_path)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    cli.wait_tick(5, run, timeout=240)
    report = attack(cli, "stop", 60, 0, out / "logs" / "keys")
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert report["at_tick"] < sc.clock.steps - 10
    m = assert_unattacked(sc, out)
    assert m["launcher"]["rejected"]["clock"] == {"auth-bad-signature": 1}
    for aid in sc.agent_ids:
        assert m["agent_stats"][str(aid)]["rejected"] == {"auth-bad-signature": 1}, aid


def test_no_member_can_speak_as_another_member_or_as_netsim(cli, tmp_path):
    """Finding 10, one member's key (agent 2's own, nothing else): frames claiming agent 3 to
    netsim, netsim's sensor frames for agent 1, deliveries to agent 1 under the next number and
    one 32,000 ahead (the lock-out of the issue), and agent 2's own frame on agent 3's key: all
    refused and counted by reason, and the run is bit for bit the unattacked one."""
    sc, out, report = attacked_run(cli, tmp_path, "forge", member=True)
    assert report["rounds"] >= 10
    m = assert_unattacked(sc, out)
    sent = Counter(report["sent"])
    assert m["rejected"]["tx"] == {"auth-bad-tag": sent["tx/auth-bad-tag"]}
    st = m["agent_stats"]["1"]
    got = dict(st["rejected"])
    # A forgery under the next number that arrives after netsim's own has a consumed number:
    # refused, before its tag, as a copy.
    assert got.pop("auth-bad-signature") == sent["1/auth-bad-signature"]
    assert got.pop("auth-bad-delivery") + got.pop("rx-out-of-sequence", 0) == sent["1/auth-bad-delivery"]
    assert got == {}
    assert st["deliveries_lost"] == 0
    for aid in sc.agent_ids:
        if aid != 1:
            assert m["agent_stats"][str(aid)]["rejected"] == {}, aid


def test_only_an_agents_own_fresh_answer_is_its_stats(cli, tmp_path):
    """Finding 3, outsider: a stranger answering `agent/*/stats` with the agents' captured, sealed
    answers and with junk used to rewrite metrics.json's agent_stats. Now each answer must hold
    the query's nonce under its agent's seal: the stranger's are refused and counted, and every
    agent's own counters are what metrics.json holds."""
    sc, path = short(tmp_path, 300.0)  # long enough for the stranger's queryable to be up before the end
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    report = attack(cli, "stats", 20, 0, timeout=400)
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert report["captured"] == len(sc.agent_ids) and report["queries"] >= 1
    m = assert_unattacked(sc, out)
    sent = Counter(report["sent"])
    # netsim stops listening once every agent has answered: what it heard of the stranger's is counted.
    for reason, n in m["rejected"]["stats"].items():
        assert n <= sent[f"stats/{reason}"], reason
    for aid in sc.agent_ids:
        st = m["agent_stats"][str(aid)]
        assert st["id"] == aid and st["k"] == sc.clock.steps  # its own, at the end, not the captured ones


def test_a_sensor_frame_counts_only_at_the_agent_it_was_sealed_for(cli, tmp_path):
    """Finding 2, outsider: netsim's sealed sensor frames for agent 1, replayed to agent 4 as soon
    as they appear, moved UKF-DCL's mean error from 1.83 to 8.80 m. netsim now addresses each
    sensor frame under its seal: agent 4 refuses every copy (misaddressed) and the run is bit for
    bit the unattacked one."""
    sc, path = short(tmp_path)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    report = attack(cli, "sensors", 20, sc.clock.steps - 50)
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert report["rounds"] >= 50
    m = assert_unattacked(sc, out)
    # The receiver is under the seal: refused at agent 4's door, before any MAC.
    assert m["agent_stats"]["4"]["rejected"] == {"auth-misaddressed": report["sent"]["4/misaddressed"]}
