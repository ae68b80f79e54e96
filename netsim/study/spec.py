"""What a study is: its spec (the pydantic models below; their field descriptions are the
documentation, docs/study.md), the plan of runs it expands to, and the result it comes to."""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from swarmloc.errors import readable

STUDY_FORMAT = 1
PATH_PATTERN = r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$"
# Nested metric dicts reported by their mean: NEES and NIS averages (results._average_with_bounds).
NESTED = ("nees", "nis")
RUN_COLUMNS = ("ticks",)  # deterministic per-run columns of results.csv (the stat_* columns follow)
TIMING_COLUMNS = ("wall_s", "cpu_s")  # never the same twice: timing.csv, not results.csv
# The run's posterior Cramér-Rao bound (swarmloc.experiment.results.metrics, docs/estimators.md):
# summarized beside the spec's metrics whenever the runs have it.
BOUND_COLUMNS = ("pcrb_m", "rmse_over_pcrb")
MAX_TIME_LINES = 8  # error_vs_time.png: one line per point up to this many points, else the first point only


class StudyError(ValueError):
    """A study spec or output directory that cannot be used; the message names the field."""


class RunFailed(RuntimeError):
    """A run raised: the study stops (finished runs are kept; rerun to retry)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SweepParam(_Strict):
    param: str = Field(pattern=PATH_PATTERN, description="dotted path of a scenario field, as in `overrides` "
                       "(e.g. radio.range_m, sensors.range.noise, estimator.params.M)")
    values: list[Any] | None = Field(None, min_length=1, description="the values it takes; the study's points are "
                                     "the cartesian product of every parameter's values")
    same_as: str | None = Field(None, pattern=PATH_PATTERN, description="instead of values: take the value of "
                                "this other swept parameter at every point (tied parameters add no grid axis)")

    @model_validator(mode="after")
    def _one_source(self):
        if (self.values is None) == (self.same_as is None):
            raise ValueError(f"{self.param}: give exactly one of values and same_as")
        return self


class StudySpec(_Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", description="study name; default output directory studies/<name>/")
    scenario: str = Field(description="built-in scenario name (`swarmloc scenarios`) or a YAML file, relative to the "
                          "spec file's directory")
    overrides: dict[str, Any] = Field(default_factory=dict, description="fixed overrides of every run, dotted path: "
                                      "value (e.g. {clock.duration: 60, radio.range_m: 300})")
    estimator: str | None = Field(None, description="the estimator the agents run, with its default settings "
                                  "(set estimator.params.* in overrides); null: the scenario's")
    references: list[str] | None = Field(None, description="offline references computed from each run's sensor "
                                         "stream; null: the scenario's")
    sweep: list[SweepParam] = Field(default_factory=list, description="swept parameters, each with values or "
                                    "same_as; empty: one point, the scenario with its overrides")
    runs: int = Field(10, ge=1, description="Monte Carlo runs per point (`--runs` overrides)")
    base_seed: int = Field(0, ge=0, description="run r of every point has seed base_seed + r")
    metrics: list[str] = Field(["mean_error_m"], min_length=1, description="columns of results.csv summarized in "
                               "summary.csv and plotted against each swept parameter (results.csv has them all)")
    settle: float = Field(0.0, ge=0, description="seconds: every metric is computed over the ticks with t >= settle "
                          "(a start-up transient left out; the final error is the last tick's either way); 0: ticks 1..")
    agents: list[int] = Field(default_factory=list, description="agents whose own metrics get columns too: "
                              "a<id>_<metric> (e.g. a4_tracking_rmse_m) for every per-agent metric")
    workers: int | None = Field(None, ge=1, description="local worker processes (`--workers` overrides); null: "
                                "the CPU count")
    scheduler: str | None = Field(None, description="address of a Dask distributed scheduler, e.g. "
                                  "tcp://10.0.0.5:8786 (`--scheduler` overrides); null: the local process pool")

    @field_validator("overrides")
    @classmethod
    def _paths(cls, v):
        import re

        for path in v:
            if not re.fullmatch(PATH_PATTERN, path):
                raise ValueError(f"{path!r} is not a dotted path like sensors.range.noise")
            if path == "seed":
                raise ValueError("seed is set per run (base_seed + run), not an override")
        return v

    @field_validator("estimator")
    @classmethod
    def _known_estimator(cls, v):
        from swarmloc.estimators import REGISTRY

        if v is not None and v not in REGISTRY.running():
            raise ValueError(f"unknown estimator {v!r}; agents run one of {sorted(REGISTRY.running())}")
        return v

    @field_validator("references")
    @classmethod
    def _known_references(cls, v):
        from swarmloc.estimators import REGISTRY

        bad = [r for r in v or () if r not in REGISTRY.references()]
        if bad:
            raise ValueError(f"unknown references {bad}; known: {sorted(REGISTRY.references())}")
        return v

    @model_validator(mode="after")
    def _sweep_consistent(self):
        names = [p.param for p in self.sweep]
        for i, p in enumerate(self.sweep):
            if names.index(p.param) != i:
                raise ValueError(f"sweep.{i}.param: {p.param} is swept twice")
            if p.param == "seed":
                raise ValueError(f"sweep.{i}.param: seed is set per run (base_seed + run), not swept")
            if p.param in self.overrides:
                raise ValueError(f"sweep.{i}.param: {p.param} is also a fixed override")
            if p.same_as is not None:
                src = next((q for q in self.sweep if q.param == p.same_as), None)
                if src is None or src.values is None:
                    raise ValueError(f"sweep.{i}.same_as: {p.same_as} is not a swept parameter with values "
                                     f"(swept: {', '.join(q.param for q in self.sweep if q.values is not None) or 'none'})")
        return self


def _validation_lines(exc: ValidationError) -> list[str]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"])
        msg = readable(err)
        out.append(f"{loc}: {msg}" if loc else msg)
    return out


def parse_spec(data, source: str = "<study>", base: Path | None = None) -> StudySpec:
    """A validated spec; a relative scenario path is taken relative to `base` (the spec's directory)."""
    if not isinstance(data, dict):
        raise StudyError(f"{source}: a study spec is a YAML mapping, got {type(data).__name__}")
    try:
        spec = StudySpec.model_validate(data)
    except ValidationError as exc:
        raise StudyError(f"{source}: " + "; ".join(_validation_lines(exc))) from None
    p = Path(spec.scenario)
    if base is not None and not p.is_absolute() and (p.suffix in (".yaml", ".yml") or (base / p).exists()):
        spec = spec.model_copy(update={"scenario": str(base / p)})
    return spec


def load_spec(path: str | Path) -> StudySpec:
    path = Path(path)
    if not path.is_file():
        raise StudyError(f"{path}: no such study spec")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise StudyError(f"{path}: not valid YAML: {exc}") from None
    return parse_spec(data, str(path), path.parent)


# ------------------------------------------------------------------------------------ the plan


@dataclass
class Plan:
    """A spec resolved against its scenario: the points, the overrides of each, the hash."""

    spec: StudySpec
    scenario_name: str
    scenario_data: dict  # the base scenario (Scenario.model_dump()): what every task starts from
    params: list[str]  # swept parameters, in sweep order (tied ones included)
    points: list[dict[str, Any]]  # param -> value
    fixed: dict[str, Any]  # overrides common to every point, estimator and references included
    spec_hash: str

    def overrides(self, point: int) -> list[tuple[str, Any]]:
        """Ordered (path, value) overrides of a point: a changed estimator first (with default settings)."""
        changes = {**self.fixed, **self.points[point]}
        out = []
        name = changes.pop("estimator.name", None)
        if name is not None and name != self.scenario_data["estimator"]["name"]:
            out.append(("estimator", {"name": name, "params": {}}))
        elif name is not None:
            out.append(("estimator.name", name))
        if "estimator" in changes:
            out.insert(0, ("estimator", changes.pop("estimator")))
        return out + list(changes.items())

    def task(self, point: int, run: int) -> dict:
        return {"scenario": self.scenario_data, "source": self.scenario_name, "overrides": self.overrides(point),
                "seed": self.spec.base_seed + run, "point": point, "run": run, "settle": self.spec.settle,
                "agents": list(self.spec.agents)}


def _grid(spec: StudySpec) -> list[dict[str, Any]]:
    axes = [p for p in spec.sweep if p.values is not None]
    points = []
    for combo in itertools.product(*(p.values for p in axes)):
        chosen = dict(zip((p.param for p in axes), combo))
        points.append({p.param: chosen[p.param if p.values is not None else p.same_as] for p in spec.sweep})
    return points


def _canonical(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def _missing_field(data: dict, path: str, scenario: str) -> str | None:
    """Why a dotted path cannot be set in the scenario, if an intermediate field is missing."""
    node, done = data, []
    for part in path.split(".")[:-1]:
        if not isinstance(node, dict):
            return f"{'.'.join(done)} is a {type(node).__name__}, not a mapping: no field {part} in it"
        if part not in node:
            where = ".".join(done) or "the top level"
            return f"scenario {scenario} has no field {'.'.join([*done, part])} ({where} has: {', '.join(node)})"
        node = node[part]
        done.append(part)
    if not isinstance(node, dict):
        return f"{'.'.join(done)} is a {type(node).__name__}, not a mapping"
    return None


def _scenario_error(exc: Exception) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines()[1:]] or [str(exc)]
    return "; ".join(lines)


def build_scenario(data: dict, source: str, overrides: Iterable[tuple[str, Any]], seed: int):
    from swarmloc.experiment import scenario as S

    return S.parse(data, source=source).with_overrides(**dict(overrides), seed=seed)


def plan(spec: StudySpec) -> Plan:
    """Resolve a spec: load its scenario and check every override path and every point before
    any run (an error names the field)."""
    from swarmloc.experiment import scenario as S

    try:
        base = S.load(spec.scenario)
    except S.ScenarioError as exc:
        raise StudyError(f"scenario: {exc}") from None
    data = base.model_dump()
    fixed: dict[str, Any] = {}
    if spec.estimator is not None:
        fixed["estimator.name"] = spec.estimator
    if spec.references is not None:
        fixed["references"] = list(spec.references)
    fixed.update(spec.overrides)
    points = _grid(spec)
    hashed = {"format": STUDY_FORMAT, "scenario": data, "fixed": fixed, "sweep": [p.model_dump() for p in spec.sweep],
              "base_seed": spec.base_seed}
    # Only when set, so the hash of a study that uses neither is what it was before they existed.
    if spec.settle:
        hashed["settle"] = spec.settle
    if spec.agents:
        hashed["agents"] = list(spec.agents)
    h = hashlib.sha256(_canonical(hashed).encode()).hexdigest()[:16]
    p = Plan(spec, base.name, data, [s.param for s in spec.sweep], points, fixed, h)
    _check(p)
    return p


def _check(p: Plan) -> None:
    from netsim.sim import channel_of
    from swarmloc.experiment.scenario import ScenarioError

    seed, name = p.spec.base_seed, p.scenario_name
    est = _only(p).overrides(0)  # the estimator and references alone

    def attempt(where: str, overrides: list[tuple[str, Any]]) -> None:
        try:
            channel_of(build_scenario(p.scenario_data, name, overrides, seed))
        except (ScenarioError, KeyError, TypeError) as exc:
            raise StudyError(f"{where}: {_scenario_error(exc)}") from None

    for path, value in p.spec.overrides.items():
        why = _missing_field(p.scenario_data, path, name)
        if why:
            raise StudyError(f"overrides.{path}: {why}")
        attempt(f"overrides.{path}", [*est, (path, value)])
    for i, s in enumerate(p.spec.sweep):
        why = _missing_field(p.scenario_data, s.param, name)
        if why:
            raise StudyError(f"sweep.{i}.param ({s.param}): {why}")
    for i, point in enumerate(p.points):
        attempt(f"sweep point {i} ({point_label(point) or 'no sweep'})", p.overrides(i))


def _only(p: Plan) -> Plan:
    """The plan with only its estimator and references as overrides, and one empty point."""
    fixed = {k: v for k, v in p.fixed.items() if k in ("estimator.name", "references")}
    return Plan(p.spec, p.scenario_name, p.scenario_data, [], [{}], fixed, p.spec_hash)


def point_label(point: dict) -> str:
    return ", ".join(f"{k}={cell_text(v)}" for k, v in point.items())


def cell_text(v) -> str:
    """A CSV cell: floats as repr (round-trips, so equal numbers give equal files), missing empty."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (int, float, str)):
        return repr(v) if isinstance(v, float) else str(v)
    return json.dumps(v, sort_keys=True)


@dataclass
class StudyResult:
    out: Path
    total: int  # runs in the study (points x runs)
    done: int  # runs finished, this call and earlier ones
    executed: int  # runs this call computed
    complete: bool  # every run done: the tables (and plots) are written
    rows: list[dict] = field(default_factory=list)  # results.csv as dicts (only when complete)
    metrics: list[str] = field(default_factory=list)  # the summarized columns: the spec's, then BOUND_COLUMNS
    summary: list[dict] = field(default_factory=list)  # summary.csv as dicts (only when complete)
    files: list[Path] = field(default_factory=list)
