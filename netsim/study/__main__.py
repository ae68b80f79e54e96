"""`python -m netsim.study SPEC`: what `swarmloc study` runs (docs/study.md)."""

from __future__ import annotations

from pathlib import Path

from netsim.study.execute import run_study
from netsim.study.spec import RunFailed, StudyError, load_spec
from netsim.study.tables import summary_table


def main(argv=None) -> int:
    """`python -m netsim.study SPEC`: what `swarmloc study` runs (docs/study.md)."""
    import argparse
    import sys

    from swarmloc.process import console

    p = argparse.ArgumentParser(prog="swarmloc study", description=__doc__.splitlines()[0])
    p.add_argument("spec", type=Path)
    p.add_argument("--out", "-o", type=Path)
    p.add_argument("--runs", type=int)
    p.add_argument("--workers", type=int)
    p.add_argument("--scheduler")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--force", action="store_true")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    # Every stop signal is an interruption: finished runs kept, the resume hint printed. SIGINT is
    # set explicitly, as a process started with it ignored (a background job) keeps it ignored.
    import signal

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, interrupt)
    err, out = console(stderr=True), a.out
    try:
        s = load_spec(a.spec)
        out = out or Path("studies") / s.name
        result = run_study(s, out, runs=a.runs, workers=a.workers, scheduler=a.scheduler, plots=not a.no_plots,
                           force=a.force, console=err)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RunFailed as exc:
        print(f"error: {exc}; the finished runs are kept in {out}/runs.jsonl", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        again = " ".join(["swarmloc study", str(a.spec), "--out", str(out), *(["--runs", str(a.runs)] if a.runs else []),
                          *(["--scheduler", a.scheduler] if a.scheduler else [])])
        print(f"interrupted: the finished runs are kept in {out}/runs.jsonl; resume with: {again}", file=sys.stderr)
        return 130
    if a.json:  # summary.csv's rows, typed, for scripts; the closing line goes to stderr then
        import json

        from netsim.study.tables import json_default

        rows = [{k: None if isinstance(v, float) and v != v else v for k, v in r.items()} for r in result.summary]
        print(json.dumps(rows, default=json_default, indent=1))  # NaN (no value) as null: strict JSON
    else:
        console().print(summary_table(result, result.metrics or s.metrics, [q.param for q in s.sweep]))
    print(f"{result.executed} runs computed, {result.done - result.executed} taken from {out}/runs.jsonl; "
          f"wrote {', '.join(str(f.relative_to(out)) for f in result.files)} in {out}", file=sys.stderr if a.json else None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
