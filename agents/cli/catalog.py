"""`swarmloc estimators` and `swarmloc scenarios`: what the agents can run, and the built-in scenarios."""

from __future__ import annotations

import json
from typing import Optional

import typer

from agents.cli.common import console, scenarios_module

app = typer.Typer()
JsonOpt = typer.Option(False, "--json", help="print the list as JSON, one object per row, for scripts")


def _show(rows: list[dict], as_json: bool) -> None:
    """Rows as a table, or as JSON (the same keys, typed values)."""
    if as_json:
        typer.echo(json.dumps(rows, indent=1))
        return
    from rich.table import Table

    t = Table(*rows[0])
    for r in rows:
        t.add_row(*(", ".join(v) if isinstance(v, list) else "yes" if v is True else "" if v is False else str(v)
                    for v in r.values()))
    console().print(t)


@app.command("estimators")
def list_estimators(as_json: bool = JsonOpt):
    """List the estimators: what agents can run (scenario `estimator`, --estimator) and the
    references computed offline from a run's sensor stream (scenario `references`)."""
    from swarmloc.estimators import REGISTRY

    _show([{"name": e.name, "agents": e.runs_on_agents, "reference": e.reference, "models": list(e.models),
            "paper": e.paper, "what it does": e.description} for e in REGISTRY], as_json)


@app.command("scenarios")
def list_scenarios(name: Optional[str] = typer.Argument(None, metavar="NAME", help="print this built-in scenario's YAML, to copy and edit"),
                   as_json: bool = JsonOpt):
    """List the built-in scenarios, or print one as YAML (swarmloc scenarios goel10 > mine.yaml)."""
    from importlib import resources

    if name is not None:
        if name not in scenarios_module().builtin_names():
            raise typer.BadParameter(f"no built-in scenario {name!r}; built-in: {', '.join(scenarios_module().builtin_names())}",
                                     param_hint=["NAME"])
        typer.echo(resources.files("swarmloc.experiment.scenarios").joinpath(f"{name}.yaml").read_text(), nl=False)
        return
    rows = []
    for name in scenarios_module().builtin_names():
        sc = scenarios_module().load(name)
        radio = " ".join([sc.radio["model"], *([f"{sc.radio['range_m']:g} m"] if "range_m" in sc.radio else [])])
        rows.append({"name": name, "agents": len(sc.world.agents),
                     **({"duration_s": sc.clock.duration, "dt_s": sc.clock.dt} if as_json else
                        {"duration": f"{sc.clock.duration:g} s @ {sc.clock.dt:g} s"}),
                     "radio": radio, "estimator": sc.estimator.name, "description": sc.description})
    _show(rows, as_json)
