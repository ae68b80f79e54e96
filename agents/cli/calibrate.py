"""`swarmloc calibrate`: a recording's noise model, fitted against its own ground truth
(swarmloc/datasets/calibrate.py), written as noise.yaml for `swarmloc replay --noise`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from agents.cli.common import console, in_range
from agents.control import Failure

app = typer.Typer()


def load_noise(path: Path | None):
    """The NoiseModel of a --noise file (None: none given); a bad file is one `error:` line, exit 2."""
    if path is None:
        return None
    from swarmloc.datasets.calibrate import CalibrationError, NoiseModel

    try:
        return NoiseModel.load(path)
    except CalibrationError as exc:
        raise Failure(str(exc), 2) from None


def model_table(model):
    """What a noise model holds, per robot, as a rich table."""
    from rich.table import Table

    t = Table("robot", "lags v / w (s)", "table cells", "speed std (m/s)", "turn-rate std (rad/s)",
              "landmarks: range std / m, bearing std (rad)", "robots: range std / m, bearing std (rad)",
              title=f"noise model of {model.recording}, fitted on "
                    + ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in model.windows)
                    + f" (white-equivalent over {model.horizon:g} s, {model.folds} cross-validation folds)")
    for r, n in sorted(model.robots.items()):
        o = n.odometry

        def cam(c):
            return "-" if c is None else f"{c.range_std_per_m:.4f}, {c.bearing_std:.4f}"

        t.add_row(f"Robot{r}", f"{o.speed_lag:.3f} / {o.turn_rate_lag:.3f}", str(len(o.table)), f"{o.speed_std:.4f}",
                  f"{o.turn_rate_std:.4f}", cam(n.landmarks), cam(n.robots))
    return t


@app.command()
def calibrate(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="an MR.CLAM dataset directory (e.g. MRCLAM_Dataset6)"),
    out: Path = typer.Option(..., "--out", "-o", help="the noise model to write (YAML, e.g. noise.yaml)"),
    window: Optional[str] = typer.Option(None, "--window", help="fit on FROM:TO seconds from the recording's start "
                                         "(several: 0:200,400:600); default: the whole recording"),
    dt: float = typer.Option(0.1, "--dt", callback=in_range(0, above=True), help="the replay's tick (s)"),
    horizon: Optional[float] = typer.Option(None, "--horizon", callback=in_range(0, above=True),
                                            help="seconds over which the stds are white-equivalent (default 10)"),
    folds: Optional[int] = typer.Option(None, "--folds", callback=in_range(1),
                                        help="cross-validation blocks per window behind the stds (default 2; 1: in "
                                        "sample)"),
    force: bool = typer.Option(False, "--force", help="overwrite --out if it exists"),
    as_json: bool = typer.Option(False, "--json", help="print the noise model as JSON (noise.yaml's fields) instead "
                                 "of the table, for scripts (`wrote ...` goes to stderr)"),
):
    """Fit a recording's noise model against its Vicon truth: per robot, the odometry's lags and
    command corrections, the camera's range and bearing bias for landmarks and for robots, and
    the std of what is left (docs/replay.md). `swarmloc replay --noise` plays a recording through it."""
    from swarmloc.datasets import calibrate as cal
    from swarmloc.datasets import mrclam

    if out.exists() and not force:
        raise Failure(f"{out} exists; pass --force to overwrite it", 2)
    try:
        rec = mrclam.load(recording)
    except mrclam.MrclamError as exc:
        raise Failure(str(exc), 2) from None
    try:
        windows = cal.parse_windows(window) if window else None
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="'--window'") from None
    try:
        model = cal.calibrate(rec, windows, dt, cal.HORIZON if horizon is None else horizon,
                              cal.FOLDS if folds is None else folds)
    except cal.CalibrationError as exc:
        raise Failure(str(exc), 2) from None
    try:
        model.save(out)
    except OSError as exc:
        raise Failure(f"{out}: cannot write: {exc.strerror or exc}", 2) from None
    if as_json:
        typer.echo(json.dumps(model.model_dump(mode="json"), indent=1))
    else:
        console().print(model_table(model))
    # stdout is the model's alone with --json: a script parses it whole.
    console(stderr=as_json).print(f"wrote {out}")
