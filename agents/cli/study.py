"""`swarmloc study`: Monte Carlo sweeps, run as netsim's process (`python -m netsim.study`)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from agents.cli.common import in_range

app = typer.Typer()


@app.command()
def study(
    spec: Path = typer.Argument(..., metavar="SPEC", help="study spec (YAML, docs/study.md)"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="study directory; rerun with the same one to resume "
                                       "(default: studies/<name>)"),
    runs: Optional[int] = typer.Option(None, "--runs", callback=in_range(1), help="runs per point, instead of the spec's"),
    workers: Optional[int] = typer.Option(None, "--workers", callback=in_range(1),
                                          help="local worker processes, instead of the spec's (default: CPU count)"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="run on this Dask distributed scheduler, e.g. "
                                            "tcp://10.0.0.5:8786, instead of the local process pool"),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="write plots/*.png into the study directory"),
    force: bool = typer.Option(False, "--force", help="discard the runs of a different study in --out"),
    as_json: bool = typer.Option(False, "--json", help="print the summary (summary.csv's rows) as JSON instead of the "
                                 "table"),
):
    """Monte Carlo study: sweep scenario parameters, many seeded in-process runs per point, in
    parallel; resumable after Ctrl-C; writes results.csv, summary.csv and plots."""
    import signal
    import subprocess

    from swarmloc.process import die_with_parent

    # The study drives netsim's world and radio, so it runs as netsim's process, as `run` does.
    args = [str(spec), *(["--out", str(out)] if out else []), *(["--runs", str(runs)] if runs else []),
            *(["--workers", str(workers)] if workers else []), *(["--scheduler", scheduler] if scheduler else []),
            *([] if plots else ["--no-plots"]), *(["--force"] if force else []), *(["--json"] if as_json else [])]
    # The child has a process group of its own, so a signal reaches it once, from us, whoever sent
    # it: a terminal's Ctrl-C (sent to our group) or `kill -INT` of our pid alike. It stops, keeps
    # the finished runs and says how to resume; a second one abandons the runs in progress.
    child = subprocess.Popen([sys.executable, "-m", "netsim.study", *args], process_group=0,
                             preexec_fn=die_with_parent())
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    previous = {s: signal.signal(s, lambda signum, _: child.send_signal(signum)) for s in stops}
    try:
        code = child.wait()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    raise typer.Exit(code)

