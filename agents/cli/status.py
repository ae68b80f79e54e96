"""`swarmloc status` and `stop`: watch a running swarm (from netsim, or from the agents
themselves when there is no netsim) and end it."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from typing import Optional

import typer

from agents.cli.common import ConnectOpt, SwarmOpt, console, in_range
from agents.control import ControlClient, NobodyAnswers, NotRunning

app = typer.Typer()


@app.command()
def stop(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """End a running swarm after its current tick; the run directory is written as at a normal end."""
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("stop")
    typer.echo(f"stopping after tick {data['k']} of {data['steps']} (t = {data['t']:.1f} s)")


def _faults_text(s: dict) -> str:
    return ", ".join(f"#{f['id']} {f['action']} {json.dumps(f['args'])}" for f in s["faults"]) or "none"


AGENT_COLUMNS = ("alive: its process holds its Zenoh liveliness token. responsive: netsim has not given up on it "
                 "(lockstep gives up an agent silent for 10 s, real time one that far behind). A killed agent is not "
                 "alive but still responsive: it was killed, not given up.")


def _agent_state(aid: int, a: dict, faults: list[dict]) -> str:
    """An agent's row in words: what alive and responsive mean together."""
    kill = next((f for f in faults if f["action"] == "kill" and f["args"].get("node") == aid), None)
    if kill is not None:
        until = "" if kill.get("until") is None else f" until t = {kill['until']:.1f} s, then restarted"
        return f"[yellow]killed by fault #{kill['id']}{until}[/]"
    if not a["alive"]:
        return "[red]down: no process (crashed, or restarting and not back yet)[/]"
    if not a["responsive"]:
        return "[red]given up: too long silent; the swarm runs on without it[/]"
    return "running"


def _status_view(s: dict):
    from rich.console import Group
    from rich.table import Table

    head = f"scenario {s['scenario']} ({s['mode']}, {s['radio']} radio): tick {s['k']}/{s['steps']}, t = {s['t']:.1f} s"
    agents = Table("agent", "alive", "responsive", "last tick done", "state", title="agents", caption=AGENT_COLUMNS,
                   caption_justify="left")
    for aid, a in s["agents"].items():
        agents.add_row(aid, "yes" if a["alive"] else "[red]no[/]", "yes" if a["responsive"] else "[red]no[/]",
                       str(a["done_k"]), _agent_state(int(aid), a, s["faults"]))
    links = Table("link", "up", "distance (m)", "SNR (dB)", "last SINR (dB)", "model PDR", "delivered", "dropped",
                  "delivery ratio", "last heard (s)", title="links")
    for l in s["links"]:
        fmt = lambda v, f="{:.2f}": "-" if v is None or v != v else f.format(v)
        links.add_row(f"{l['a']}-{l['b']}", "up" if l["up"] else f"[red]down ({l['reason']})[/]", f"{l['distance']:.1f}",
                      fmt(l["snr_db"], "{:.1f}"), fmt(l.get("sinr_db"), "{:.1f}"), fmt(l["pdr_model"]),
                      str(l["delivered"]), str(l["dropped"]),
                      fmt(l["delivery_ratio"]), fmt(l["last_heard"], "{:.1f}"))
    return Group(head, agents, links, f"faults: {_faults_text(s)}")


def _status_line(s: dict) -> str:
    alive = sum(a["alive"] for a in s["agents"].values())
    up = sum(l["up"] for l in s["links"])
    return (f"tick {s['k']}/{s['steps']} t={s['t']:.1f}s agents alive {alive}/{len(s['agents'])} "
            f"links up {up} down {len(s['links']) - up} faults {_faults_text(s)}")


def _sources_text(sources: dict) -> str:
    """A daemon's polled sources in a few words: a flight controller's link, a recording's progress."""
    def one(name: str, st: dict) -> str:
        if "link" in st:
            return f"{name}: {st['link']}, tick {st['tick']}"
        if "of" in st:
            more = [f", {v} {k}" for k, v in st.items() if k not in ("frames", "of") and isinstance(v, int) and v]
            return f"{name}: {st['frames']}/{st['of']} frames{''.join(more)}"
        return f"{name}: {json.dumps(st)}"

    return "\n".join(one(n, st) for n, st in sources.items()) or "-"


def _clock_text(d: dict) -> str:
    """A direct-mode agent's estimate of each peer's clock offset to its own (agents/timesync.py)
    with its uncertainty, flagged when beyond its bound by more than that, and how many estimates
    were."""
    bound = d.get("clock_bound_ms", 10.0)

    def one(peer, c) -> str:
        # +- half the round trip: how far off the offset can be (a first sample may have queued).
        half = c.get("round_trip_ms", 0.0) / 2
        text = f"{peer}: {c['offset_ms']:+.1f}±{half:.1f} ms"
        return f"[red]{text}[/]" if abs(c["offset_ms"]) - half > bound else text

    parts = [one(p, c) for p, c in sorted(d.get("clock_offset_ms", {}).items(), key=lambda i: int(i[0]))]
    if d.get("clock_exceeded"):
        parts.append(f"[red]{d['clock_exceeded']} beyond {bound:g} ms[/]")
    return ", ".join(parts) or "-"


def _agents_view(a: dict):
    from rich.console import Group
    from rich.table import Column, Table

    rows = a["rows"]
    answering = sum(r["reply_ms"] is not None for r in rows)
    head = f"swarm {a['swarm']}: {answering}/{len(rows)} agents answer on swarmloc/{a['swarm']}/agent/*/stats"
    # `peers` is shown once the daemons report it; today's stats do not.
    peers = any("peers" in r["data"] for r in rows if r["data"])
    clocks = any("clock_offset_ms" in r["data"] for r in rows if r["data"])
    t = Table("agent", "estimator", "tick", "ticks", "skipped", *(["peers"] if peers else []),
              *(["clock offset to peers"] if clocks else []), "rejected",
              "node drops", Column("sources", overflow="fold"), "alive", "heard", title="agents")
    for r in rows:
        d = r["data"]
        alive = "yes" if r["alive"] else "[red]no[/]"
        # Answering now: how long its answer took (its loop's latency); silent: since when.
        if r["reply_ms"] is not None:
            heard = f"{r['reply_ms']:.0f} ms"
        else:
            heard = "[red]never[/]" if r["heard_s"] is None else f"[red]{r['heard_s']:.1f} s ago[/]"
        if d is None:  # a token, but never an answer: its loop is stuck, or it is not a swarmloc daemon
            t.add_row(str(r["id"]), "-", "-", "-", "-", *(["-"] if peers else []), *(["-"] if clocks else []), "-", "-",
                      "-", alive, heard)
            continue
        t.add_row(str(r["id"]), d["algorithm"], str(d["k"]), str(d["ticks"]), str(d["ticks_skipped"]),
                  *([", ".join(map(str, d.get("peers", []))) or "none"] if peers else []),
                  *([_clock_text(d)] if clocks else []),
                  str(sum(d["rejected"].values())), str(sum(d["node_drops"].values())),
                  _sources_text(d.get("sources", {})), alive, heard)
    extra = [f"unreadable reply on {key}: {why}" for key, why in a["unreadable"].items()]
    return Group(head, t, *extra)


def _agents_line(a: dict) -> str:
    rows = a["rows"]

    def one(r: dict) -> str:
        if r["reply_ms"] is not None:
            return f"{r['id']} {r['data']['algorithm']} tick {r['data']['k']}"
        return f"{r['id']} silent" + ("" if r["heard_s"] is None else f" for {r['heard_s']:.1f}s")

    shown = [one(r) for r in rows]
    return f"agents answer {sum(r['reply_ms'] is not None for r in rows)}/{len(rows)}: {', '.join(shown)}"


def _agents_rounds(ctl: ControlClient, watch: bool, interval: float):
    """The agents' answers, round after round with --watch; an agent that stops answering keeps
    its last row, with how long ago it was last heard."""
    last: dict[int, tuple[dict, float]] = {}  # agent id: its last stats, and when they came
    first = True
    while True:
        ans = ctl.agents()
        if first and not (ans.stats or ans.alive or ans.unreadable):
            raise NobodyAnswers(ctl.swarm, ctl.endpoints)
        first = False
        now = time.monotonic()
        last.update((aid, (data, now)) for aid, data in ans.stats.items())
        rows = []
        for aid in sorted(set(last) | ans.alive):
            data, heard = last.get(aid, (None, None))
            rows.append({"id": aid, "data": data, "alive": aid in ans.alive,
                         "reply_ms": ans.reply_s[aid] * 1e3 if aid in ans.reply_s else None,
                         "heard_s": None if heard is None else now - heard})
        yield {str(aid): data for aid, data in sorted(ans.stats.items())}, \
            {"swarm": ctl.swarm, "rows": rows, "unreadable": ans.unreadable}
        if not watch:
            return
        time.sleep(interval)


def _show(rounds, view, line, as_json: bool, watch: bool) -> bool:
    """Print each (raw, shown) round: the raw answer as JSON, a rich view, or with --watch off a
    terminal one plain line; on a terminal --watch redraws in place. False after Ctrl-C."""
    try:
        if watch and not as_json and sys.stdout.isatty():
            from rich.live import Live

            with Live(console=console(), refresh_per_second=4) as live:
                for _, shown in rounds:
                    live.update(view(shown))
        else:
            for raw, shown in rounds:
                if as_json:
                    typer.echo(json.dumps(raw))
                elif watch:
                    typer.echo(line(shown))
                else:
                    console().print(view(shown))
    except KeyboardInterrupt:
        # Ctrl-C is the way out of --watch: if closing the Zenoh session then hangs (a query in
        # flight), the process still ends, cleanly, 2 s later, as exit_on_sigterm does for SIGTERM.
        watchdog = threading.Timer(2.0, os._exit, args=(0,))
        watchdog.daemon = True
        watchdog.start()
        return False
    return True


@app.command()
def status(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt,
           as_json: bool = typer.Option(False, "--json", help="print the raw status as JSON (from the agents: "
                                        "their stats, keyed by agent id)"),
           watch: bool = typer.Option(False, "--watch", "-w", help="refresh until Ctrl-C or the run ends "
                                      "(not on a terminal: one plain line per refresh)"),
           interval: float = typer.Option(0.5, "--interval", callback=in_range(0, above=True),
                                          help="seconds between refreshes with --watch"),
           agents: bool = typer.Option(False, "--agents", help="ask the agents for their own counters, not netsim "
                                       "(what status does when no netsim answers)")):
    """Show a running swarm: tick, agents alive, link table (SNR, delivery ratio, last heard), faults.
    Without netsim (agents on a direct radio), each agent's own counters."""
    if watch:
        # Ctrl-C ends --watch even when we were started with SIGINT ignored (a background job
        # of a non-interactive shell, as the launcher also handles).
        signal.signal(signal.SIGINT, signal.default_int_handler)
    client = ControlClient(swarm, connect)
    try:
        with client as ctl:
            first = None
            if not agents:
                try:
                    first = ctl.request("status")
                except NotRunning:
                    pass  # no netsim: the agents may still answer for themselves
            if first is None:
                _show(_agents_rounds(ctl, watch, interval), _agents_view, _agents_line, as_json, watch)
                return

            def statuses():
                yield first, first
                while watch:
                    time.sleep(interval)
                    try:
                        s = ctl.request("status")
                    except NotRunning:  # the run ended under our eyes: the normal way out
                        return
                    yield s, s

            ended = _show(statuses(), _status_view, _status_line, as_json, watch)
    except NotRunning:  # no session at all: nothing listens there
        raise NobodyAnswers(swarm, client.endpoints) from None
    if watch and ended:
        typer.echo("netsim is gone: the run has ended")
