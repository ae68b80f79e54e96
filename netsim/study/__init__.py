"""Monte Carlo studies: sweep scenario parameters, many seeded runs per point (docs/study.md).

The room: spec.py (the spec, its plan and result), execute.py (running the plan), tables.py and
plots.py (what a finished study writes), __main__.py (`python -m netsim.study`). This module
is the front door.

A study spec (YAML, the pydantic models below; their field descriptions are the documentation)
names a scenario, fixed overrides, the swept parameters and the number of runs. Every run is
one in-process run (swarmloc.experiment.runner.InProcessRunner over netsim.sim.Simulation) of the
scenario with the point's overrides and seed `base_seed + run`, followed by the offline
references and `swarmloc.experiment.results.metrics`. A run depends on nothing else, so the same spec
gives the same results.csv whoever executes it: the local process pool (default) or a Dask
distributed cluster (`scheduler`). Dask is imported only when a scheduler is given.

Finished runs are appended to OUT/runs.jsonl one line each (flushed and fsynced), so an
interrupted study resumes where it stopped; the tables and plots are written when every run
is done.
"""

from netsim.study.execute import run_study, run_task
from netsim.study.spec import Plan, RunFailed, StudyError, StudyResult, StudySpec, load_spec, parse_spec, plan
from netsim.study.tables import result_rows, summary_table, write_tables

__all__ = ["Plan", "RunFailed", "StudyError", "StudyResult", "StudySpec", "load_spec", "parse_spec", "plan",
           "run_study", "run_task", "result_rows", "summary_table", "write_tables"]
