"""`swarmloc run`, `demo`, `replay` and `rerun`: a swarm of agent processes with netsim, from a
scenario, an MR.CLAM recording or a run's run.mcap (agents/launcher.py does the work)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from agents.cli.common import (
    DurationOpt,
    EstimatorOpt,
    ForceOpt,
    OutOpt,
    PlotsOpt,
    PortOpt,
    RealtimeOpt,
    RestartOpt,
    RunSwarmOpt,
    SeedOpt,
    SpeedOpt,
    console,
    estimator_name,
    in_range,
    load_scenario,
    parse_ids,
    scenarios_module,
)
from agents.control import Failure

app = typer.Typer()

RecordOpt = typer.Option(True, "--record/--no-record", help="write run.mcap, every frame and the Foxglove view, as the "
                         "run goes (docs/run-format.md#runmcap)")
ViewOpt = typer.Option(None, "--view", callback=in_range(0, 65535), metavar="PORT",
                       help="serve the live view over the Foxglove WebSocket protocol on ws://127.0.0.1:PORT (0: a "
                            "free port, said in netsim.log); open it in Foxglove with 'Open connection'")
Ros2DomainOpt = typer.Option(None, "--ros2-domain", callback=in_range(0, 232), metavar="ID",
                             help="also publish every estimate on ROS 2 topics of ROS_DOMAIN_ID ID, as rmw_zenoh "
                                  "does (docs/ros2.md)")
Ros2NamespaceOpt = typer.Option("/swarmloc", "--ros2-namespace", help="--ros2-domain: the topics' namespace")
Ros2DistroOpt = typer.Option("jazzy", "--ros2-distro", help="--ros2-domain: jazzy (type hashes, Jazzy and later) or "
                             "humble (no type hashes)")


def netsim_args(record: bool, view: int | None, ros2_domain: int | None = None, ros2_namespace: str = "/swarmloc",
                ros2_distro: str = "jazzy") -> tuple[str, ...]:
    """netsim's options for the recording, the live view and ROS 2 (checked here: one-line errors)."""
    if ros2_domain is not None:
        from swarmloc.wire.ros2 import Ros2Error, Topics

        try:
            Topics(ros2_domain, ros2_namespace, ros2_distro)
        except Ros2Error as exc:
            raise Failure(str(exc), 2) from None
    return (*([] if record else ["--no-record"]), *([] if view is None else ["--view", str(view)]),
            *([] if ros2_domain is None else ["--ros2-domain", str(ros2_domain), "--ros2-namespace", ros2_namespace,
                                              "--ros2-distro", ros2_distro]))


PerProcessOpt = typer.Option(1, "--agents-per-process", callback=in_range(1), metavar="K",
                             help="run K agents in each agent process, served by one loop, each with its own "
                                  "session, keys and checkpoint: the same on the wire, a fraction of the memory")
JsonOpt = typer.Option(False, "--json", help="print metrics.json on stdout at the end instead of the summary tables "
                       "(the progress and messages go to stderr)")


def _run(scenario: str, out: Path | None, seed: int | None, swarm: str | None, port: int | None, plots: bool,
         force: bool, restart_crashed: bool, estimator: str | None = None, realtime: bool | None = None,
         speed: float | None = None, duration: float | None = None, as_json: bool = False,
         extra: tuple[str, ...] = (), per_process: int = 1) -> None:
    from agents.launcher import run_swarm

    run_swarm(load_scenario(scenario, seed, estimator, realtime, speed, duration), out, swarm, port, plots, force,
              restart_crashed, as_json=as_json, netsim_args=extra, per_process=per_process)


@app.command()
def run(
    scenario: str = typer.Argument(..., metavar="SCENARIO", help="built-in scenario name (see `swarmloc scenarios`) or a YAML file"),
    out: Optional[Path] = OutOpt, seed: Optional[int] = SeedOpt, swarm: Optional[str] = RunSwarmOpt,
    port: Optional[int] = PortOpt, plots: bool = PlotsOpt, force: bool = ForceOpt, restart_crashed: bool = RestartOpt,
    estimator: Optional[str] = EstimatorOpt, realtime: Optional[bool] = RealtimeOpt, speed: Optional[float] = SpeedOpt,
    duration: Optional[float] = DurationOpt, as_json: bool = JsonOpt, record: bool = RecordOpt,
    view: Optional[int] = ViewOpt, ros2_domain: Optional[int] = Ros2DomainOpt, ros2_namespace: str = Ros2NamespaceOpt,
    ros2_distro: str = Ros2DistroOpt, per_process: int = PerProcessOpt,
):
    """Run a scenario: netsim plus one agent process per platform, over Zenoh on loopback.

    A crashed agent is reported and the run goes on without it; only a failing netsim fails the run."""
    _run(scenario, out, seed, swarm, port, plots, force, restart_crashed, estimator, realtime, speed, duration, as_json,
         netsim_args(record, view, ros2_domain, ros2_namespace, ros2_distro), per_process)


@app.command()
def demo(out: Optional[Path] = OutOpt, seed: Optional[int] = SeedOpt, swarm: Optional[str] = RunSwarmOpt,
         port: Optional[int] = PortOpt, plots: bool = PlotsOpt, force: bool = ForceOpt,
         restart_crashed: bool = RestartOpt, realtime: Optional[bool] = RealtimeOpt, speed: Optional[float] = SpeedOpt,
         duration: Optional[float] = DurationOpt, as_json: bool = JsonOpt, record: bool = RecordOpt,
         view: Optional[int] = ViewOpt, per_process: int = PerProcessOpt):
    """Run the built-in wang2019 scenario (UKF-DCL paper, 4 platforms, 801 ticks)."""
    _run("wang2019", out, seed, swarm, port, plots, force, restart_crashed, None, realtime, speed, duration, as_json,
         netsim_args(record, view), per_process)


# What `replay` sets from its options, by option: its errors name the option.
REPLAY_OPTIONS = {"world.path": "PATH", "world.offset": "--offset", "world.robots": "--robots", "clock.dt": "--dt",
                  "clock.duration": "--duration", "clock.speed": "--speed", "estimator": "--estimator",
                  "estimator.name": "--estimator", "estimation.gate": "--gate", "seed": "--seed",
                  "world.noise": "--noise"}


def replay_odometry_bias(given: bool | None, landmarks: bool, odometry_horizon: float | None) -> tuple[bool, str]:
    """Whether a replay's ukf-dcl, ekf-ccl and ukf-ccl carry odometry bias states, and what its
    label adds when that is the default. Given (--odometry-bias/--no-odometry-bias): as given. By
    default on without landmarks, where nothing absolute pins the formation and the odometry's
    lasting error accumulates over the whole run: with a calibrated model the filters miss a mean
    NEES of 6 without them (6.07-6.09 over Dataset6, each half held out) and meet it with them
    (3.11-3.13 at the default walks, RMSE 9-10 % better than before calibration; docs/replay.md).
    Off with landmarks (there they cost accuracy on held-out data, docs/mrclam.md) and with the
    white noise of before (--odometry-horizon), which the bias states were never measured with."""
    if given is not None:
        return given, ""
    if landmarks or odometry_horizon is not None:
        return False, ""
    return True, " (the default without landmarks; --no-odometry-bias: without)"


@app.command()
def replay(
    path: Path = typer.Argument(..., metavar="PATH", help="an MR.CLAM dataset directory (e.g. MRCLAM_Dataset6)"),
    estimator: str = typer.Option("ukf-dcl", "--estimator", callback=estimator_name, help="what the agents run"),
    dt: float = typer.Option(0.1, "--dt", callback=in_range(0, above=True), help="tick (s)"),
    duration: Optional[float] = typer.Option(None, "--duration", callback=in_range(0, above=True),
                                             help="seconds to replay (default: to the recording's end)"),
    offset: Optional[float] = typer.Option(None, "--offset", callback=in_range(0),
                                           help="start this many seconds in (default: with neither --offset nor "
                                           "--duration, the second half, the first calibrating the noise)"),
    robots: Optional[str] = typer.Option(None, "--robots", help="replay only these robots, e.g. 1,2,3"),
    landmarks: bool = typer.Option(True, "--landmarks/--no-landmarks", help="deliver landmark observations (known map)"),
    observations: bool = typer.Option(True, "--observations/--no-observations",
                                      help="deliver the robots' observations of each other"),
    gate: Optional[float] = typer.Option(0.999, "--gate", callback=in_range(0),
                                         help="chi-square gate probability; 0 turns the gate off"),
    noise: Optional[Path] = typer.Option(None, "--noise", help="play the recording through this noise model "
                                         "(`swarmloc calibrate`) instead of calibrating on the part it does not score"),
    fit_on_scored: bool = typer.Option(False, "--fit-on-scored", help="calibrate on the scored data itself (the "
                                       "output says so)"),
    odometry_horizon: Optional[float] = typer.Option(None, "--odometry-horizon", callback=in_range(0, above=True),
                                                     help="the uncalibrated white noise of before `calibrate`, its "
                                                     "odometry fitted over this many seconds (docs/replay.md)"),
    odometry_bias: Optional[bool] = typer.Option(None, "--odometry-bias/--no-odometry-bias",
                                                 help="ukf-dcl and the ekf-ccl and ukf-ccl references with per-robot "
                                                 "odometry bias states (docs/mrclam.md) (default: on with --no-landmarks and "
                                                 "a calibrated noise model, off otherwise)"),
    realtime: bool = typer.Option(False, "--realtime", help="tick at the recording's pace (times --speed) "
                                  "instead of as fast as the agents go"),
    speed: Optional[float] = typer.Option(None, "--speed", callback=in_range(0, above=True),
                                          help="with --realtime: recorded seconds per wall second [default: 1]"),
    out: Optional[Path] = OutOpt, seed: Optional[int] = SeedOpt, swarm: Optional[str] = RunSwarmOpt,
    port: Optional[int] = PortOpt, plots: bool = PlotsOpt, force: bool = ForceOpt, as_json: bool = JsonOpt,
    record: bool = RecordOpt, view: Optional[int] = ViewOpt,
):
    """Replay a recorded MR.CLAM dataset through the agent processes (Leung et al., IJRR 2011):
    netsim plays each robot's odometry and range-bearing observations on the sensor keys, its
    Vicon poses drive the radio and score the estimates. Prints position and heading RMSE and
    NEES per robot and estimator; writes the usual run directory.

    The noise model is fitted on a part of the recording the run does not score (by default the
    first half, scoring the second), or given (--noise), or fitted on the scored data
    (--fit-on-scored); the output says which."""
    from agents.cli.calibrate import load_noise
    from agents.launcher import run_swarm
    from swarmloc.estimators import REGISTRY
    from swarmloc.experiment.replay import replay_label, replay_scenario

    if REGISTRY[estimator].requires:  # csl-ctl and il-ctl localize targets; a recording has none
        raise typer.BadParameter(f"{estimator} localizes targets, and an MR.CLAM recording has none: its agents would "
                                 "run dead reckoning alone", param_hint=["--estimator"])
    if speed is not None and not realtime:
        raise typer.BadParameter("a lockstep replay goes as fast as the agents do and has no speed; add --realtime",
                                 param_hint=["--speed"])
    if sum((noise is not None, fit_on_scored, odometry_horizon is not None)) > 1:
        raise typer.BadParameter("one of --noise, --fit-on-scored and --odometry-horizon", param_hint=["--noise"])
    model = load_noise(noise)
    bias, why = replay_odometry_bias(odometry_bias, landmarks, odometry_horizon)
    sc = scenarios_module()
    try:
        scenario = replay_scenario(path, estimator=estimator or "ukf-dcl", dt=dt, duration=duration, offset=offset,
                                   robots=parse_ids(robots, "--robots") if robots else None, landmarks=landmarks,
                                   observations=observations, gate=gate or None,
                                   mode="realtime" if realtime else "lockstep", speed=speed or 1.0, seed=seed or 0,
                                   noise=model, calibration="scored" if fit_on_scored else "held-out",
                                   odometry_horizon=odometry_horizon, odometry_bias=bias)
    except sc.ScenarioError as exc:
        raise Failure(str(exc.renamed(f"replay of {path}", REPLAY_OPTIONS)), 2) from None
    label = replay_label(scenario) + (why if scenario.reference_params else "")
    say = console(stderr=True) if as_json else console()
    say.print(label)
    run_swarm(scenario, out, swarm, port, plots, force, False, as_json=as_json, netsim_args=netsim_args(record, view))
    say.print(label)


@app.command()
def rerun(
    recordings: list[Path] = typer.Argument(..., metavar="RECORDING...", help="a run's run.mcap (written by "
                                            "`swarmloc run`), or agents' own recordings (outputs.record), one per agent"),
    estimator: Optional[str] = EstimatorOpt,
    out: Optional[Path] = OutOpt, swarm: Optional[str] = RunSwarmOpt, port: Optional[int] = PortOpt,
    plots: bool = PlotsOpt, force: bool = ForceOpt, as_json: bool = JsonOpt, record: bool = RecordOpt,
    view: Optional[int] = ViewOpt,
):
    """Run fresh agent processes on recorded sensor frames: netsim plays the clock, sensor frames
    and truth of a run's run.mcap again, with the run's scenario, seed and radio, or the frames of
    agents' own recordings. With the recorded estimator, a lockstep rerun reproduces the run's
    estimates bit for bit; --estimator runs another one on the same inputs
    (docs/cli.md#swarmloc-rerun)."""
    from agents.launcher import run_swarm
    from swarmloc.experiment.recording import RecordingError, rerun_scenario

    sc = scenarios_module()
    for recording in recordings:
        if not recording.is_file():
            raise Failure(f"{recording}: no such file", 2)
    try:
        scenario = rerun_scenario(recordings, estimator)
    except (RecordingError, sc.ScenarioError) as exc:
        raise Failure(str(exc), 2) from None
    run_swarm(scenario, out, swarm, port, plots, force, False, as_json=as_json, netsim_args=netsim_args(record, view))


@app.command()
def results(
    run_dir: Path = typer.Argument(..., metavar="DIR", help="a run directory (`swarmloc run --out DIR`)"),
    rebuild: bool = typer.Option(False, "--rebuild", help="rebuild metrics.json from run.mcap even if it is there"),
    plots: bool = PlotsOpt, as_json: bool = JsonOpt,
):
    """A run's results: its summary tables; for a run that ended before netsim wrote them (netsim
    or the launcher killed), metrics.json, estimates and plots rebuilt first from its run.mcap,
    up to the last finished tick (docs/run-format.md)."""
    from agents.summary import print_summary
    from swarmloc.experiment.recording import RecordingError
    from swarmloc.experiment.rundir import rebuild_run

    if not run_dir.is_dir():
        raise Failure(f"{run_dir}: no such directory", 2)
    if rebuild or not (run_dir / "metrics.json").is_file():
        try:
            m = rebuild_run(run_dir, plots)
        except RecordingError as exc:
            raise Failure(str(exc), 2) from None
        e = m.get("ended_early")
        console(stderr=as_json).print(f"rebuilt {run_dir / 'metrics.json'} from {run_dir / 'run.mcap'}: ticks "
                                            f"0..{m['ticks'] - 1}" + (f" of {e['ticks_planned']}" if e else ""),
                                            highlight=False)
    if as_json:
        typer.echo((run_dir / "metrics.json").read_text())
        return
    print_summary(run_dir, [], console())
