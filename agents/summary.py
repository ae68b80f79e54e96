"""The summary of a run, as `swarmloc run` prints it at the end and `swarmloc results` prints it
for a run directory: the result tables read from its metrics.json, and the notes that say in
words what the tables do not (the columns' roles, identical estimators, one worse than a
baseline, radio drops, dropped measurements, crashed agents)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Protocol, Sequence

from rich.table import Table

from swarmloc.estimators import REGISTRY
from swarmloc.process import console as process_console


class CrashRecord(Protocol):
    """What the summary says of a crashed agent (the launcher's Crash, agents/launcher.py)."""

    restarted: bool

    def describe(self) -> str: ...


def consistency_table(m: dict, algs: list[str]) -> Table:
    """Average NEES (and NIS) of each estimator over agents and ticks, with the two-sided 95%
    chi-square bounds a consistent filter's average falls in."""
    t = Table(title="Consistency: average NEES and NIS (95% bounds)")
    for col in ("estimator", "NEES", "bounds", "", "NIS", "bounds", ""):
        t.add_column(col, justify="left" if col == "estimator" else "right")

    def cells(c):
        if not c:
            return ["-", "", ""]
        lo, hi = c["bounds"]
        return [f"{c['mean']:.2f}", f"[{lo:.2f}, {hi:.2f}]", "[green]inside[/]" if c["inside"] else "[red]outside[/]"]

    for a in algs:
        e = m["estimators"][a]
        t.add_row(a, *cells(e.get("nees")), *cells(e.get("nis")))
    return t


def target_table(m: dict, algs: list[str]) -> Table:
    """Each target-localizing estimator's target error (m): averaged over the agents and the
    ticks they had an estimate, and over the agents at the last tick; and its NEES."""
    t = Table(title="Target error (m), over agents")
    for col in ("estimator", "target", "mean", "final", "NEES", "bounds"):
        t.add_column(col, justify="left" if col in ("estimator", "target") else "right")
    for a in algs:
        for o, e in m["estimators"][a].get("targets", {}).items():
            n = e.get("nees")
            t.add_row(a, o, *("-" if v is None else f"{v:.2f}" for v in (e["mean_error_m"], e["final_error_m"])),
                      "-" if not n else f"{n['mean']:.2f}", "" if not n else f"[{n['bounds'][0]:.2f}, {n['bounds'][1]:.2f}]")
    return t


def pose_table(m: dict, algs: list[str]) -> Table:
    """Per agent and estimator: position RMSE (m), heading RMSE (rad) and average NEES, for a
    swarm whose states carry a heading (a replay's robots)."""
    t = Table(title="Per agent: position RMSE (m), heading RMSE (rad), NEES (3 dof when consistent)", show_lines=True)
    t.add_column("estimator")
    t.add_column("")
    for aid in m["agents"]:
        t.add_column(f"A{aid}", justify="right")
    t.add_column("all", justify="right")

    def cell(e):
        nees = e.get("nees")
        parts = [f"{e['rmse_m']:.3f}" if e.get("rmse_m") is not None else "-",
                 f"{e['heading_rmse_rad']:.3f}" if e.get("heading_rmse_rad") is not None else "-",
                 f"{nees['mean']:.1f}" if nees else "-"]
        return "\n".join(parts)

    for a in algs:
        e = m["estimators"][a]
        t.add_row(a, "position RMSE (m)\nheading RMSE (rad)\nNEES", *(cell(e["agents"][str(aid)]) for aid in m["agents"]),
                  cell(e))
    return t


ROLES = {"agents": "what the agent processes ran",
         "baseline": "no cooperation, or a naive one: what cooperating must beat",
         "reference": "the centralized filter over the whole swarm, computed offline from the same sensor stream: what "
                      "a distributed one should match",
         "offline": "computed offline from the same sensor stream"}
# Radio drop reasons (metrics.json radio.dropped; docs/radio.md) in words.
DROPS = {"distance": "out of radio range", "sinr": "SINR too low", "collision": "collided", "half-duplex":
         "the receiver was sending", "queue": "queue full", "fault": "on a cut link", "partition": "across a partition",
         "radio-off": "radio off", "jammed": "jammed", "loss": "extra loss (fault)", "down": "to or from an agent down"}
WORSE = 1.1  # one run's mean error this much above a baseline's is worth a word; closer is one seed's noise
DROP_WARN = 0.1  # in real time, a larger share of measurements dropped is the machine not keeping up


def roles(m: dict, algs: list[str]) -> dict[str, str]:
    """Each estimator's part in the run: what the agents ran, a baseline, the reference."""
    out = {}
    for a in algs:
        info = REGISTRY.get(a)
        parts = ["agents" if a == m.get("estimator") else "", info.role if info else ""]
        out[a] = ", ".join(p for p in parts if p) or "offline"
    return out


def _m(v: float) -> str:
    return f"{v:.3g} m"


def summary_notes(m: dict, algs: list[str]) -> list[str]:
    """What the tables do not say by themselves, in words: the columns' roles, estimators that
    gave the same estimates, one doing worse than a baseline (and whether the formation tells
    why), the ground stations, the radio's drops, measurements the agents dropped."""
    role = roles(m, algs)
    est = m["estimators"]
    used = sorted({r for a in algs for r in role[a].split(", ")}, key=list(ROLES).index)
    notes = ["; ".join(f"{r}: {ROLES[r]}" for r in used) + "."]
    for same in m.get("identical", []):
        a, b = same["estimators"]
        d = same["max_difference_m"]
        notes.append(f"{a} and {b} gave the same position estimates ({'exactly' if d == 0 else f'to {d:.1g} m'}): their "
                     f"columns are equal, and the plots draw {b} dashed over {a}.")
    copies = {s["estimators"][1] for s in m.get("identical", [])}  # said once, of the first of a pair
    noted: set[str] = set()
    for base in (a for a in algs if "baseline" in role[a] and a not in copies and est[a]["mean_error_m"] is not None):
        worse = [a for a in algs if "baseline" not in role[a] and a not in copies | noted
                 and est[a]["mean_error_m"] is not None and est[a]["mean_error_m"] > WORSE * est[base]["mean_error_m"]]
        noted.update(worse)
        for a in worse:
            text = (f"{a} ({role[a]}) is worse than the baseline {base} here: {_m(est[a]['mean_error_m'])} against "
                    f"{_m(est[base]['mean_error_m'])} on average.")
            fa, fb = est[a].get("formation_rmse_m"), est[base].get("formation_rmse_m")
            if fa is not None and fb is not None and fa < fb:
                text += (f" Its formation is better ({_m(fa)} against {_m(fb)} RMS once the swarm's common shift and "
                         "turn are taken out): measurements among the agents fix the swarm's shape, not where it is or "
                         "which way it is turned; without an absolute measurement (GNSS, landmarks) that common part is "
                         "not corrected, and in one run it can drift further than the agents' own dead reckoning.")
            notes.append(text)
    ground = m.get("ground_stations") or []
    if ground:
        ids = ", ".join(map(str, ground))
        notes.append(f"agent{'s' if len(ground) > 1 else ''} {ids}: ground station{'s' if len(ground) > 1 else ''} "
                     "(a fusion centre's process); no position of its own to estimate, so no row.")
    r = m.get("radio", {})
    dropped = r.get("dropped") or {}
    why = ", ".join(f"{n} {DROPS.get(k, k)}" for k, n in sorted(dropped.items(), key=lambda kv: -kv[1]))
    if m.get("wall_time_s") is None:  # rebuilt from the recording: no wall time, no radio counts
        notes.append(f"{m['ticks']} ticks, rebuilt from {m.get('rebuilt_from', 'the recording')}")
    else:
        notes.append(f"{m['ticks']} ticks in {m['wall_time_s']:.1f} s ({m['ticks_per_s']:.0f} ticks/s); radio: "
                     f"{r.get('delivered', 0)} frames delivered, " + (f"{sum(dropped.values())} dropped ({why})"
                                                                         if dropped else "none dropped"))
    if m.get("ended_early"):
        e = m["ended_early"]
        notes.append(f"[red]the run ended early: {e['why']}; ticks 0..{e['last_tick']} of {e['ticks_planned']}[/]")
    notes.extend(measurement_drops(m))
    if "error" in m.get("pcrb", {}):
        notes.append(f"[yellow]no PCRB for this run ({m['pcrb']['error']}): the numbers above stand, without the bound "
                     "beside them.[/]")
    return notes


def measurement_drops(m: dict, realtime: bool | None = None) -> list[str]:
    """The measurements the agents' estimator dropped (those with `measurements_dropped` in their
    stats: UKF-DCL), in words; in real time a large share is the machine falling behind."""
    stats = [s for s in (m.get("agent_stats") or {}).values() if "measurements_dropped" in s]
    dropped = sum(s["measurements_dropped"] for s in stats)
    total = dropped + sum(s.get("measurements_used", 0) for s in stats)
    if not dropped:
        return []
    realtime = m.get("transport") == "zenoh-realtime" if realtime is None else realtime
    share = dropped / total
    text = (f"the agents ({m.get('estimator')}) dropped {dropped} of their {total} measurements ({share:.0%}): "
            "chains that did not finish within their tick, or to platforms out of reach")
    if realtime and share > DROP_WARN:
        return [f"[yellow]{text}. In real time that is the machine not keeping up: the results are those of a filter "
                "that saw fewer measurements. Lower --speed, or run in lockstep (run --lockstep, replay without "
                "--realtime), which waits.[/]"]
    return [text + "."]


def print_summary(out: Path, crashes: Sequence[CrashRecord], ui=None) -> None:
    """The run directory's summary, printed on ui (default: the command's console): the
    position error table, consistency, per-agent pose and target tables when the run has them,
    the notes, the crashes."""
    ui = process_console() if ui is None else ui
    m = json.loads((out / "metrics.json").read_text())
    algs = REGISTRY.order(m["estimators"])
    role = roles(m, algs)
    pcrb = m.get("pcrb", {}).get("rms_m")  # the run's posterior Cramér-Rao bound (swarmloc/experiment/bounds.py)
    t = Table(title=f"Position error (m), {m['scenario']} seed {m['seed']}"
              + ("; RMSE / PCRB: 1 is the best any estimator can do on average" if pcrb else ""))
    t.add_column("agent")
    for a in algs:  # headers over lines: a long estimator name does not widen two columns
        t.add_column(f"{a}\n{role[a]}\nmean", justify="right")
        t.add_column(f"{a}\n{role[a]}\nfinal", justify="right")
        if pcrb:
            t.add_column(f"{a}\n{role[a]}\nRMSE / PCRB", justify="right")
    if pcrb:
        t.add_column("PCRB\n\nrms", justify="right")

    def fmt(v):
        return "-" if v is None else f"{v:.3f}" if abs(v) < 1 else f"{v:.2f}"

    for aid in map(str, m["agents"]):
        row = [f"A{aid}"]
        for a in algs:
            e = m["estimators"][a]["agents"][aid]
            row += [fmt(e["mean_error_m"]), fmt(e["final_error_m"])] + ([fmt(e.get("rmse_over_pcrb"))] if pcrb else [])
        t.add_row(*row, *([fmt(pcrb.get(aid))] if pcrb else []))
    t.add_row("all", *sum(([fmt(m["estimators"][a]["mean_error_m"]), ""]
                           + ([fmt(m["estimators"][a].get("rmse_over_pcrb"))] if pcrb else []) for a in algs), []),
              *([""] if pcrb else []), style="bold")
    ui.print(t)
    ui.print(consistency_table(m, algs))
    if any(m["estimators"][a].get("heading_rmse_rad") is not None for a in algs):
        ui.print(pose_table(m, algs))
    if any("targets" in m["estimators"][a] for a in algs):
        ui.print(target_table(m, algs))
    for note in summary_notes(m, algs):
        ui.print(note, highlight=False)
    for c in crashes:
        then = "restarted from its checkpoint" if c.restarted else "left out from then on (its estimates stop there)"
        ui.print(f"[yellow]{c.describe()}; {then}[/]", soft_wrap=True)
    plots = ", plots/*.png" if (out / "plots").is_dir() else ""
    mcap = ", run.mcap" if (out / "run.mcap").is_file() else ""
    ui.print(f"run directory: [bold]{out}[/] (metrics.json, estimates/*.npz{plots}{mcap})")
