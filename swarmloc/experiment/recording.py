"""run.mcap: a run recorded as it goes, as MCAP (format: docs/run-format.md, "run.mcap").

Two kinds of channels in one file:

- the wire: every frame that crossed Zenoh, on a channel named by its key expression
  (`swarmloc/<swarm>/agent/1/sensors`, ...), message encoding `msgpack`, no schema, the payload
  the bytes exactly as they went over Zenoh (docs/wire.md). With them the recording is the
  complete, replayable record of the run: `swarmloc rerun` plays its sensor frames again,
  `load` rebuilds the run record and its metrics from it.
- the view: what Foxglove draws with no setup, in schemas of the Foxglove SDK (protobuf): the
  scene (truth, every estimator's positions with their 95 % ellipses, the radio links coloured by
  SNR or state, landmarks and targets, the faults in force as a label), faults and membership
  events as log entries, and each agent's error and NEES per estimator as plottable JSON series.

Message times (log_time) are the run's start (UNIX ns) plus modelled time, so Foxglove's
timeline is the run's clock. The writer (foxglove-sdk's, chunked, lz4) finishes a chunk at least
every FLUSH_PERIOD of wall time: a recording cut short by a crash (kill -9) reads to its last
complete chunk (`messages` stops there and says so).

No sockets here: the processes give `Recorder` a foxglove Context they may also serve live
(netsim's `--view`), and call it from their loops. netsim's recorder is `deferred`: it holds the
calls and does them when netsim's loop would otherwise wait (`drain`), because in lockstep every
agent waits for netsim between a round's last `done` and the next frame, so work done there,
the tick's view above all, delays every agent's next step (docs/benchmarks.md, "run.mcap: what
the recording costs").
"""

from __future__ import annotations

import functools
import json
import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
from msgspec.structs import replace

from swarmloc import wire
from swarmloc.wire.messages import Clock, EstimateMsg, Sensors, Truth

FORMAT_VERSION = 1
WIRE_ENCODING = "msgpack"
META = "swarmloc"  # the metadata record describing the run
PROFILE = "swarmloc"
FLUSH_PERIOD = 1.0  # s of wall time between two finished chunks
ELLIPSE_CHI2 = 5.991464547107979  # chi-square quantile 0.95 with 2 degrees of freedom

SCENE, STATIC, FAULTS, EVENTS, TARGETS = "/scene", "/scene/static", "/faults", "/events", "/truth/targets"
TRUTH_HISTORY = 64  # ticks of truth kept for scoring estimates that arrive late (real time)
# Calls a deferred recorder holds before it does them at once anyway: a loop that is never idle
# (a real-time run beyond the machine) must not grow them without bound.
MAX_HELD = 20_000
_METRICS_FIELDS = {"k": {"type": "integer"}, "t": {"type": "number"}, "error_m": {"type": "number"},
                   "nees": {"type": "number"}, "dof": {"type": "integer"}}


def metrics_topic(algorithm: str, aid: int) -> str:
    return f"/metrics/{algorithm}/{aid}"


def withheld_key(keys: wire.Keys, aid: int) -> str:
    """The channel of the sensor frames netsim made for an agent but did not publish (its process
    was down or killed): the references and a rerun use them like the others."""
    return f"{keys.prefix}/netsim/withheld/{aid}"


# --------------------------------------------------------------------------- writing


def _rgba(color: str, alpha: float = 1.0):
    from foxglove.messages import Color
    from matplotlib.colors import to_rgba

    r, g, b, _ = to_rgba(color)
    return Color(r=r, g=g, b=b, a=alpha)


def _deferrable(impl):
    """A Recorder call that a deferred recorder holds until `drain`; held calls run in the order
    they were made, on arguments nobody changes afterwards, so the file is the one an immediate
    recorder writes."""

    @functools.wraps(impl)
    def call(self, *args, **kw):
        if self._held is None:
            return impl(self, *args, **kw)
        self._held.append((impl, args, kw))
        if len(self._held) >= MAX_HELD:
            self.drain()

    return call


@dataclass
class _Agent:
    model: object  # swarmloc.models.motion.MotionModel
    label: str


class Recorder:
    """The writer of one run.mcap (or, with path None, only the channels of a live view).

    meta: the run's description, written as the metadata record `swarmloc` (values made strings;
    dicts and lists as JSON). scenario: the run's scenario (agents' models, landmarks, targets),
    or None (an agent's own recording: no scene). The caller feeds it frames (`frame`), each
    tick's truth (`truth`), estimates (`estimate`), the link table (`links`), faults and events,
    and ends every tick with `end_tick`, which draws the scene and flushes when it is due.
    deferred: those calls are held until `drain` (or `close`); `pending` says some are."""

    def __init__(self, path: Path | None, meta: dict, scenario=None, context=None, start_ns: int | None = None,
                 flush_period: float = FLUSH_PERIOD, scene: bool = True, deferred: bool = False):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.context = context if context is not None else foxglove.Context()
        self.start_ns = time.time_ns() if start_ns is None else start_ns
        self.writer = None
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            opts = MCAPWriteOptions(compression=MCAPCompression.Lz4, profile=PROFILE, compression_threads=0)
            self.writer = foxglove.open_mcap(path, allow_overwrite=True, context=self.context, writer_options=opts)
            self.writer.write_metadata(META, {k: v if isinstance(v, str) else json.dumps(v) for k, v in
                                              {"format_version": FORMAT_VERSION, **meta}.items()})
        self.path = path
        self.flush_period = flush_period
        self._flushed = time.monotonic()
        self._raw: dict[str, object] = {}
        self._json: dict[str, object] = {}
        self.frames = 0
        self._held: deque | None = deque() if deferred else None  # (method, args, kwargs)
        self.sc = scenario
        self.scene_on = scene and scenario is not None
        self.agents: dict[int, _Agent] = {}
        self._truth: dict[int, np.ndarray] = {}
        self._truth_k: deque = deque(maxlen=TRUTH_HISTORY)  # (k, {aid: state})
        self._targets: dict[int, np.ndarray] = {}
        self._est: dict[str, dict[int, tuple]] = {}  # alg -> aid -> (mean, cov, targets)
        self._links: list[dict] = []
        self._pending: dict[tuple[str, int], tuple] = {}  # estimates to score at the tick's end
        self._faults: dict[str, str] = {}  # id -> description, the faults in force
        from foxglove.channels import LogChannel

        # Declared now, not at the first entry: a live viewer subscribes to what is advertised,
        # and would miss the entry that advertised its channel.
        for topic in (FAULTS, EVENTS):
            self._json[topic] = LogChannel(topic, context=self.context)
        if self.scene_on:
            self._scene_setup()

    # ---------------------------------------------------------------- channels

    def _wire_channel(self, key: str):
        # The private Context._create_channel, because foxglove-sdk 0.30 has no public way to make
        # a channel with a message encoding and no schema: foxglove.Channel takes one without a
        # schema only for JSON (it raises TypeError for "msgpack"), and with any Schema object the
        # file gets a schema record (schema_id != 0), not the schemaless wire channel of
        # docs/run-format.md. Hence the `<0.31` cap on foxglove-sdk in pyproject.toml: move to a
        # public call once one exists, before raising the cap.
        ch = self._raw.get(key)
        if ch is None:
            ch = self._raw[key] = self.context._create_channel(key, message_encoding=WIRE_ENCODING, schema=None,
                                                                metadata={"swarmloc": "wire"})
        return ch

    def _json_channel(self, topic: str, title: str, properties: dict):
        ch = self._json.get(topic)
        if ch is None:
            from foxglove import Channel

            schema = {"type": "object", "title": title, "properties": properties}
            ch = self._json[topic] = Channel(topic, schema=schema, context=self.context)
        return ch

    def ns(self, t: float) -> int:
        """log_time of modelled time t."""
        return self.start_ns + int(round(t * 1e9))

    def frame(self, key: str, data: bytes, t: float) -> None:
        """A frame that crossed Zenoh on `key`, as it went (bytes), at modelled time t."""
        self.frames += 1  # now, not when drained: the run's metrics count them before close
        if self._held is None:
            self._wire_channel(key).log(bytes(data), log_time=self.ns(t))
        else:  # spelt out, not @_deferrable: 55 frames a tick for one scene
            self._held.append((Recorder._frame, (key, bytes(data), t), None))
            if len(self._held) >= MAX_HELD:
                self.drain()

    def _frame(self, key: str, data: bytes, t: float) -> None:  # the held frame's marker (drain does it)
        self._wire_channel(key).log(data, log_time=self.ns(t))

    @property
    def pending(self) -> bool:
        return bool(self._held)

    def drain(self, deadline: float | None = None) -> None:
        """Do the held calls, in order; with `deadline` (time.perf_counter()), only until then."""
        held, raw, frame = self._held, self._raw, Recorder._frame
        last_t = ns = None
        while held:
            impl, args, kw = held.popleft()
            if impl is frame:  # most of what is held: inline, a tick's frames share one time
                key, data, t = args
                if t != last_t:
                    last_t, ns = t, self.ns(t)
                (raw.get(key) or self._wire_channel(key)).log(data, log_time=ns)
            elif kw:
                impl(self, *args, **kw)
            else:
                impl(self, *args)
            if deadline is not None and time.perf_counter() >= deadline:
                return

    # ---------------------------------------------------------------- the view's inputs

    @_deferrable
    def truth(self, k: int, t: float, states: dict[int, np.ndarray], targets: dict[int, np.ndarray]) -> None:
        self._truth = states
        self._truth_k.append((k, states))
        if targets:
            self._targets = targets
            ids = sorted(targets)
            self._json_channel(TARGETS, "swarmloc.targets", {"k": {"type": "integer"}, "t": {"type": "number"},
                                                              "ids": {"type": "array"}, "positions": {"type": "array"}}
                               ).log({"k": k, "t": t, "ids": ids, "positions": [np.asarray(targets[o], float).tolist()
                                                                                for o in ids]}, log_time=self.ns(t))

    @_deferrable
    def estimate(self, algorithm: str, aid: int, k: int, t: float, mean: np.ndarray, cov: np.ndarray,
                 targets=()) -> None:
        """An agent's estimate of tick k: kept for the scene, and its error and NEES against the
        truth of tick k on /metrics/<algorithm>/<aid> when the tick ends (an agent may publish
        several estimates of a tick as its chains commit: the last one is scored)."""
        self._est.setdefault(algorithm, {})[aid] = (mean, cov, targets)
        self._pending[(algorithm, aid)] = (k, t, mean, cov)

    def _score(self, algorithm: str, aid: int, k: int, t: float, mean: np.ndarray, cov: np.ndarray) -> None:
        a = self.agents.get(aid)
        truth = next((s for kk, s in reversed(self._truth_k) if kk == k), None)
        if a is None or truth is None or aid not in truth:
            return
        x = truth[aid]
        n = a.model.state_dim
        if n == 0 or len(mean) != n or len(x) != n:
            return
        p = a.model.position_dim
        d = mean[:p] - x[:p]
        # np.linalg.norm's own sum for a float vector (sqrt of d.dot(d)), without its checks.
        err = math.sqrt(d.dot(d)) if d.dtype == np.float64 and d.ndim == 1 else float(np.linalg.norm(d))
        try:
            e = a.model.error(x, mean)
            nees = float(e @ np.linalg.solve(cov, e))
        except (np.linalg.LinAlgError, ValueError):
            nees = None
        if not (math.isfinite(err) and (nees is None or math.isfinite(nees))):
            return
        self._json_channel(metrics_topic(algorithm, aid), "swarmloc.metrics", _METRICS_FIELDS).log(
            {"k": k, "t": t, "error_m": err, "nees": nees, "dof": n}, log_time=self.ns(t))

    @_deferrable
    def links(self, rows: list[dict]) -> None:
        self._links = rows

    def _log(self, topic: str, t: float, level, text: str, name: str) -> None:
        from foxglove.messages import Log, Timestamp

        ch = self._json[topic]
        ns = self.ns(t)
        ch.log(Log(timestamp=Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000), level=level, message=text,
                   name=name), log_time=ns)

    @_deferrable
    def fault(self, entry: dict, active: list[dict]) -> None:
        """A fault applied or cleared (an entry of netsim's fault log: k, t, source, action and its
        fields) as a log entry; `active` (FaultState.describe()): the faults in force, which the
        scene labels."""
        from foxglove.messages import LogLevel

        fields = " ".join(f"{k}={_compact(v)}" for k, v in entry.items() if k not in ("k", "t", "source", "action"))
        t = float(entry.get("t", 0.0))
        self._log(FAULTS, t, LogLevel.Warning, f"t={t:g} s: {entry.get('action')} {fields} ({entry.get('source')})",
                  "netsim")
        self._faults = {str(a["id"]): f"#{a['id']} {a['action']} " + " ".join(
            f"{k}={_compact(v)}" for k, v in a.get("args", {}).items()) for a in active}

    @_deferrable
    def event(self, t: float, text: str, level: str = "info") -> None:
        from foxglove.messages import LogLevel

        self._log(EVENTS, t, LogLevel.Warning if level == "warning" else LogLevel.Info, text, "netsim")

    # ---------------------------------------------------------------- the scene

    def _scene_setup(self) -> None:
        from swarmloc.estimators import REGISTRY
        from swarmloc.models.motion import MOTION_MODELS

        sc = self.sc
        self.agents = {a.id: _Agent(MOTION_MODELS[a.model], f"A{a.id}") for a in sc.world.agents}
        pts = [np.asarray(a.start, float)[:2] for a in sc.world.agents] + \
              [np.asarray(m.position, float)[:2] for m in sc.world.landmarks]
        span = max((float(np.linalg.norm(p - q)) for p in pts for q in pts), default=0.0)
        self.size = max(0.05, span / 80)  # a platform's marker: small against the swarm's extent
        self._colors = {}
        self._registry = REGISTRY
        self.static_logged = False

    def _color(self, algorithm: str, alpha: float = 1.0):
        key = (algorithm, alpha)
        c = self._colors.get(key)
        if c is None:
            c = self._colors[key] = _rgba(self._registry.color(algorithm), alpha)
        return c

    def _static(self, t: float) -> None:
        """Landmarks (and nothing else that never moves), once, on their own topic: Foxglove shows
        the latest message of each topic after a seek, so they stay on screen."""
        from foxglove.channels import SceneUpdateChannel
        from foxglove.messages import Color, CubePrimitive, SceneEntity, SceneUpdate, TextPrimitive

        cubes, texts = [], []
        for m in self.sc.world.landmarks:
            x, y = m.position[:2]
            pose = _pose(x, y, 0.0)
            cubes.append(CubePrimitive(pose=pose, size=_vec(self.size, self.size, self.size), color=Color(r=0.4, g=0.4,
                                                                                                          b=0.4, a=1)))
            texts.append(TextPrimitive(pose=_pose(x, y, self.size), billboard=True, font_size=12, scale_invariant=True,
                                       color=Color(r=0.3, g=0.3, b=0.3, a=1), text=f"L{m.id}"))
        ch = self._json.get(STATIC)
        if ch is None:
            ch = self._json[STATIC] = SceneUpdateChannel(STATIC, context=self.context)
        ch.log(SceneUpdate(entities=[SceneEntity(id="landmarks", frame_id="map", cubes=cubes, texts=texts)]),
               log_time=self.ns(t))
        self.static_logged = True

    @_deferrable
    def end_tick(self, k: int, t: float) -> None:
        """The tick's scene (every agent's truth, the latest estimates, links, faults); a flush
        when one is due."""
        if self._pending:
            for (alg, aid), est in self._pending.items():
                self._score(alg, aid, *est)
            self._pending.clear()
        if self.scene_on:
            if not self.static_logged:
                self._static(t)
            self._scene(t)
        if self.writer is not None and time.monotonic() - self._flushed >= self.flush_period:
            self.flush()

    def _scene(self, t: float) -> None:
        M = _fm()
        Color, CylinderPrimitive, LinePrimitive = M.Color, M.CylinderPrimitive, M.LinePrimitive
        SceneEntity, SceneUpdate, SpherePrimitive, TextPrimitive = M.SceneEntity, M.SceneUpdate, M.SpherePrimitive, \
            M.TextPrimitive
        s = self.size
        black, dot, big = _const("black"), _const(("vec", s)), _const(("vec", 1.5 * s))
        at = {}
        spheres, texts = [], []
        for aid, a in self.agents.items():
            x = self._truth.get(aid)
            if x is None or not a.model.state_dim:
                continue
            p = [float(v) for v in x[: a.model.position_dim]]
            if not all(map(math.isfinite, p)):
                continue
            z = p[2] if len(p) > 2 else 0.0
            at[aid] = (p[0], p[1], z)
            spheres.append(SpherePrimitive(pose=_pose(*at[aid]), size=dot, color=black))
            texts.append(TextPrimitive(pose=_pose(at[aid][0], at[aid][1], z + 1.5 * s), billboard=True, font_size=14,
                                       scale_invariant=True, color=black, text=a.label))
        for o, p in self._targets.items():
            spheres.append(SpherePrimitive(pose=_pose(float(p[0]), float(p[1]), 0.0), size=big,
                                           color=Color(r=0.85, g=0.1, b=0.1, a=1.0)))
            texts.append(TextPrimitive(pose=_pose(float(p[0]), float(p[1]), 2 * s), billboard=True, font_size=14,
                                       scale_invariant=True, color=Color(r=0.85, g=0.1, b=0.1, a=1.0), text=f"T{o}"))
        entities = [SceneEntity(id="truth", frame_id="map", spheres=spheres, texts=texts)]
        for alg, per in self._est.items():
            color, fill = self._color(alg), self._color(alg, 0.25)
            dots, discs = [], []
            for aid, (mean, cov, targets) in per.items():
                a = self.agents.get(aid)
                if a is None or a.model.state_dim == 0:
                    continue
                mx, my = float(mean[0]), float(mean[1])
                if not (math.isfinite(mx) and math.isfinite(my)):
                    continue
                z = float(mean[2]) if a.model.position_dim > 2 else 0.0
                dots.append(SpherePrimitive(pose=_pose(mx, my, z), size=_const(("vec", 0.8 * s)), color=color))
                disc = _ellipse(mean[:2], cov[:2, :2], z, fill, CylinderPrimitive, s)
                if disc is not None:
                    discs.append(disc)
                for _, m, P in targets:
                    dots.append(SpherePrimitive(pose=_pose(float(m[0]), float(m[1]), 0.0), size=dot,
                                                color=color))
                    disc = _ellipse(m[:2], P[:2, :2], 0.0, fill, CylinderPrimitive, s)
                    if disc is not None:
                        discs.append(disc)
            entities.append(SceneEntity(id=f"estimate/{alg}", frame_id="map", spheres=dots, cylinders=discs))
        if self._links and at:
            pts, colors = [], []
            for row in self._links:
                a, b = at.get(row["a"]), at.get(row["b"])
                if a is None or b is None:
                    continue
                c = _link_color(row)
                pts += [_pt(*a), _pt(*b)]
                colors += [c, c]
            if pts:
                entities.append(SceneEntity(id="links", frame_id="map", lines=[LinePrimitive(
                    type=M.LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True, points=pts,
                    colors=colors)]))
        if self._faults:
            text = "faults: " + "; ".join(self._faults.values())
            entities.append(SceneEntity(id="faults", frame_id="map", texts=[TextPrimitive(
                pose=_pose(0.0, 0.0, 4 * s), billboard=True, font_size=16, scale_invariant=True,
                color=Color(r=0.8, g=0.0, b=0.0, a=1.0), text=text)]))
        ch = self._json.get(SCENE)
        if ch is None:
            from foxglove.channels import SceneUpdateChannel

            ch = self._json[SCENE] = SceneUpdateChannel(SCENE, context=self.context)
        ch.log(SceneUpdate(entities=entities), log_time=self.ns(t))

    def flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()
        self._flushed = time.monotonic()

    def close(self) -> None:
        if self._held:
            self.drain()
        if self.writer is not None:
            self.writer.close()
            self.writer = None


LAYOUT = "foxglove-layout.json"  # written beside run.mcap (docs/run-format.md, "The layout")
LAYOUT_MARGIN = 1.15  # the framed box's half-sizes times this, so nothing sits on the panel's edge
LAYOUT_ASPECT = 1.3  # the 3D panel's width over its height that the framing assumes (70 % of a wide window)
LAYOUT_PLOTTED = 8  # agents whose error the layout's plot draws (the first, by id)


def layout(xy: np.ndarray, algorithm: str | None = None, agents: list[int] = ()) -> dict:
    """A layout for Foxglove (and Lichtblick, its open-source fork), the JSON their "Import
    layout" reads: a 3D panel that shows /scene and /scene/static, seen from straight above with
    x east to the right, framed on the points `xy` ((n, 2): every position the run's platforms,
    landmarks and targets took), beside a log panel of /faults over a plot of `algorithm`'s
    position error for the first LAYOUT_PLOTTED of `agents` (their /metrics series). Their 3D
    panel draws a SceneUpdate topic only once it is switched on and starts 20 m from the origin
    at an angle: without this file a user makes those settings by hand (docs/run-format.md)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    lo, hi = (xy.min(axis=0), xy.max(axis=0)) if len(xy) else (np.zeros(2), np.zeros(2))
    centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 5.0) * LAYOUT_MARGIN
    fovy = 45.0
    # A perspective camera at `distance` sees a half-height of distance * tan(fovy / 2).
    distance = max(half[1], half[0] / LAYOUT_ASPECT) / math.tan(math.radians(fovy / 2))
    three_d, log_panel, plot = "3D!swarmloc", "RosOut!swarmloc", "Plot!swarmloc"  # "RosOut": the log panel's type
    plotted = sorted(agents)[:LAYOUT_PLOTTED] if algorithm else []
    right = {"first": log_panel, "second": plot, "direction": "column", "splitPercentage": 40} if plotted else log_panel
    return {
        "configById": {
            three_d: {
                "cameraState": {"distance": round(distance, 2), "perspective": True, "phi": 0.1,
                                "target": [0, 0, 0], "targetOffset": [round(float(centre[0]), 2),
                                                                      round(float(centre[1]), 2), 0],
                                "targetOrientation": [0, 0, 0, 1], "thetaOffset": 0, "fovy": fovy, "near": 0.5,
                                "far": max(5000.0, round(4 * distance, 1))},
                "followMode": "follow-none", "followTf": "map", "scene": {}, "transforms": {},
                "topics": {SCENE: {"visible": True}, STATIC: {"visible": True}},
                "layers": {}, "publish": {}, "imageMode": {},
            },
            log_panel: {"searchTerms": [], "minLogLevel": 1, "topicToRender": FAULTS},
            **({plot: {"paths": [{"value": f"{metrics_topic(algorithm, a)}.error_m", "enabled": True,
                                  "timestampMethod": "receiveTime", "label": f"A{a}"} for a in plotted],
                       "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True,
                       "legendDisplay": "floating", "showPlotValuesInLegend": False, "isSynced": True,
                       "xAxisVal": "timestamp", "sidebarDimension": 240,
                       "foxglovePanelTitle": f"{algorithm}: position error (m)"}} if plotted else {}),
        },
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1.0},
        "layout": {"first": three_d, "second": right, "direction": "row", "splitPercentage": 70},
    }


def _compact(v) -> str:
    return json.dumps(v, separators=(",", ":")) if isinstance(v, (list, dict)) else str(v)


_FM = None


def _fm():
    """foxglove.messages, imported once (the scene is drawn every tick)."""
    global _FM
    if _FM is None:
        import foxglove.messages

        _FM = foxglove.messages
    return _FM


def _vec(x, y, z):
    return _fm().Vector3(x=x, y=y, z=z)


def _pt(x, y, z):
    return _fm().Point3(x=x, y=y, z=z)


_CONST: dict = {}


def _const(key):
    """A message part drawn every tick with the same values, made once (they are values: a
    message built with one holds a copy)."""
    v = _CONST.get(key)
    if v is None:
        m = _fm()
        if key == "black":
            v = m.Color(r=0.0, g=0.0, b=0.0, a=1.0)
        elif key == "upright":
            v = m.Quaternion(x=0.0, y=0.0, z=math.sin(0.0), w=math.cos(0.0))
        else:  # ("vec", size): a cube's sides
            v = _vec(key[1], key[1], key[1])
        _CONST[key] = v
    return v


def _pose(x, y, z, yaw: float | None = None):
    m = _fm()
    q = _const("upright") if yaw is None else m.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    return m.Pose(position=m.Vector3(x=x, y=y, z=z), orientation=q)


def _ellipse(m, P, z, color, cylinder, s):
    """The 95 % ellipse of a 2D position as a flat elliptic cylinder, or None if P is not one
    (the 2 x 2 eigen-decomposition in closed form: this runs for every agent every tick)."""
    x, y = float(m[0]), float(m[1])
    a, b, c = float(P[0, 0]), 0.5 * (float(P[0, 1]) + float(P[1, 0])), float(P[1, 1])
    if not all(map(math.isfinite, (x, y, a, b, c))):
        return None
    mid, r = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    lo, hi = mid - r, mid + r
    if lo <= 0:
        return None
    yaw = 0.5 * math.atan2(2 * b, a - c)  # of the major axis
    return cylinder(pose=_pose(x, y, z, yaw), size=_vec(2 * math.sqrt(ELLIPSE_CHI2 * hi),
                                                        2 * math.sqrt(ELLIPSE_CHI2 * lo), 0.05 * s), color=color)


def _link_color(row: dict):
    """Up: by SNR, red at 0 dB to green at 30 dB (green without an SNR: a unit disk); down:
    red for a fault's cut (fault, partition, jammed, radio off), grey when out of range or down."""
    Color = _fm().Color
    if not row.get("up"):
        if row.get("reason") in ("fault", "partition", "jammed", "radio-off"):
            return Color(r=0.9, g=0.0, b=0.0, a=0.9)
        return Color(r=0.6, g=0.6, b=0.6, a=0.5)
    snr = row.get("snr_db")
    u = 1.0 if snr is None or not math.isfinite(snr) else min(1.0, max(0.0, snr / 30.0))
    return Color(r=1.0 - u, g=0.75 * u + 0.1, b=0.1, a=0.8)


# --------------------------------------------------------------------------- reading


@dataclass
class Message:
    topic: str
    encoding: str
    log_time: int
    data: bytes


@dataclass
class Scan:
    """What `messages` found beyond the messages: the metadata records and whether the file ended
    early (an unfinished recording: everything up to its last complete chunk was read)."""

    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    truncated: bool = False
    error: str = ""


def messages(path: Path, scan: Scan | None = None, topics=None) -> Iterator[Message]:
    """Every message of an MCAP file in file order (the order it was written), even of an
    unfinished one: reading stops at the first incomplete record and sets scan.truncated."""
    from mcap.records import Channel, Metadata
    from mcap.records import Message as McapMessage
    from mcap.stream_reader import StreamReader

    scan = scan if scan is not None else Scan()
    channels: dict[int, tuple[str, str]] = {}
    with open(path, "rb") as f:
        records = StreamReader(f, skip_magic=False, emit_chunks=False).records
        while True:
            try:
                rec = next(records)
            except StopIteration:
                return
            except Exception as exc:  # mcap raises EndOfFile, InvalidMagic, CRC and length errors on a cut file
                scan.truncated, scan.error = True, f"{type(exc).__name__}: {exc}"
                return
            if isinstance(rec, Channel):
                channels[rec.id] = (rec.topic, rec.message_encoding)
            elif isinstance(rec, McapMessage):
                topic, enc = channels.get(rec.channel_id, ("", ""))
                if topics is None or topic in topics or (callable(topics) and topics(topic)):
                    yield Message(topic, enc, rec.log_time, rec.data)
            elif isinstance(rec, Metadata):
                scan.metadata[rec.name] = dict(rec.metadata)


def metadata(path: Path) -> dict:
    """The `swarmloc` metadata record of a recording (values decoded from JSON where they are),
    reading no further than the record (it is written first)."""
    from mcap.records import Metadata
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False, emit_chunks=True).records:
                if isinstance(rec, Metadata) and rec.name == META:
                    return {k: _json_or_str(v) for k, v in rec.metadata.items()}
        except Exception as exc:
            raise RecordingError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    raise RecordingError(f"{path}: no `{META}` metadata record: not a swarmloc recording")


def _json_or_str(v: str):
    try:
        return json.loads(v)
    except ValueError:
        return v


class RecordingError(ValueError):
    pass


@dataclass
class RecordedRun:
    """The wire channels of a recording, decoded: per tick, the sensor frames (published or
    withheld), truth and targets; every estimate; the metadata. Frames that fail to decode are
    counted in `bad` by topic, never raised."""

    meta: dict
    ticks: list[int] = field(default_factory=list)
    t: dict[int, float] = field(default_factory=dict)
    sensors: dict[int, dict[int, Sensors]] = field(default_factory=dict)
    truth: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)
    targets: dict[int, dict[int, np.ndarray]] = field(default_factory=dict)
    estimates: list[tuple[int, EstimateMsg]] = field(default_factory=list)
    truncated: bool = False
    bad: dict[str, int] = field(default_factory=dict)
    stopped: bool = False  # netsim's stop clock is in it: its last tick was finished

    @property
    def scenario(self):
        from swarmloc.experiment.scenario import parse

        text = self.meta.get("scenario")
        if not isinstance(text, str):
            return None
        import yaml

        return parse(yaml.safe_load(text), "the recording's scenario")


def load(path: Path) -> RecordedRun:
    """A recording's run (RecordingError if it is no swarmloc recording)."""
    path = Path(path)
    run = RecordedRun(metadata(path))
    scan = Scan()

    def bad(topic):
        run.bad[topic] = run.bad.get(topic, 0) + 1

    for m in messages(path, scan):
        if m.encoding != WIRE_ENCODING:
            if m.topic == TARGETS:
                d = json.loads(m.data)
                run.targets[d["k"]] = {o: np.array(p, float) for o, p in zip(d["ids"], d["positions"])}
            continue
        parts = m.topic.split("/")
        kind = parts[-1] if len(parts) >= 3 else ""
        try:
            if kind == "clock":
                c = wire.decode(m.data, expect=(Clock,)).body
                run.stopped |= c.mode == "stop"
                if c.mode != "stop" and c.k not in run.t:
                    run.ticks.append(c.k)
                    run.t[c.k] = c.t
            elif kind == "sensors" or (len(parts) >= 2 and parts[-2] == "withheld"):
                s = wire.decode(m.data, expect=(Sensors,)).body
                run.sensors.setdefault(s.k, {})[wire.Keys.agent_of(m.topic.replace("/netsim/withheld/", "/agent/"))] = s
            elif len(parts) >= 2 and parts[-2] == "truth":
                tr = wire.decode(m.data, expect=(Truth,)).body
                run.truth.setdefault(tr.k, {})[int(parts[-1])] = tr.state
            elif kind == "estimate":
                env = wire.decode(m.data, expect=(EstimateMsg,))
                run.estimates.append((env.src, env.body))
        except (wire.WireError, ValueError):
            bad(m.topic)
    run.truncated = scan.truncated
    if not run.ticks:  # an agent's recording has no clock of netsim's: its frames' ticks
        run.ticks = sorted(run.sensors)
        run.t = {k: next(iter(run.sensors[k].values())).t for k in run.ticks}
    return run


def record_of(run: RecordedRun, scenario=None):
    """The run record (swarmloc.experiment.results.RunRecord) a recording holds: ticks, sensor
    frames, truth, targets and the agents' estimates, as netsim gathered them; the references are
    not in it (results.compute_references adds them)."""
    from swarmloc.experiment.results import RunRecord
    from swarmloc.node import Estimate

    sc = scenario if scenario is not None else run.scenario
    if sc is None:
        raise RecordingError("the recording holds no scenario")
    record = RunRecord.for_scenario(sc)
    ids = sc.agent_ids
    for k in run.ticks:
        frames = run.sensors.get(k, {})
        frames = {a: frames.get(a) or Sensors(k, run.t[k], None, []) for a in ids}
        truth = run.truth.get(k, {})
        states = {a: truth.get(a, np.full(sc_state_dim(sc, a), np.nan)) for a in ids}
        record.add_tick(k, run.t[k], frames, states, run.targets.get(k))
    for aid, e in run.estimates:
        nis = () if e.nis is None else tuple((float(v), int(d)) for v, d in e.nis)
        record.add_estimate(e.algorithm, aid, Estimate(e.k, e.mean, e.cov, nis,
                                                       tuple((t.target, t.mean, t.cov) for t in e.targets)))
    return record


def sc_state_dim(sc, aid: int) -> int:
    from swarmloc.models.motion import MOTION_MODELS

    return MOTION_MODELS[sc.agent(aid).model].state_dim


def rerun_scenario(paths: list[Path], estimator: str | None = None, seed: int | None = None):
    """The scenario `swarmloc rerun` runs: a netsim recording's own, its world the recording
    (world.source: mcap), its agents running `estimator` (default: the recorded one); or, from
    agents' own recordings (one file each, `outputs.record` on companion computers), a scenario
    of those agents as their configurations describe them (`agents_scenario`)."""
    import yaml

    from swarmloc.experiment.scenario import parse

    paths = [Path(p).resolve() for p in paths]
    metas = [metadata(p) for p in paths]
    if all(m.get("writer") == "agent" for m in metas):
        return agents_scenario(paths, metas, estimator)
    if len(paths) != 1:
        raise RecordingError("a netsim recording is one file; several files are agents' own recordings")
    meta = metas[0]
    if not isinstance(meta.get("scenario"), str):
        raise RecordingError(f"{paths[0]}: the recording holds no scenario")
    data = yaml.safe_load(meta["scenario"])
    world = dict(data["world"])
    for k in ("robots", "odometry_lag", "stop_distance"):
        world.pop(k, None)
    world.update(source="mcap", path=str(paths[0]), offset=0.0)
    data["world"] = world
    if estimator is not None:
        data["estimator"] = {"name": estimator}
    seed = meta.get("seed") if seed is None else seed
    if isinstance(seed, int):
        data["seed"] = seed
    return parse(data, f"rerun of {paths[0]}")


def agents_scenario(paths: list[Path], metas: list[dict], estimator: str | None = None):
    """The scenario of agents' own recordings: each agent as its configuration (in the
    recording's metadata) describes it, its prior exactly its configured one, its sensor frames
    the recorded ones; ticks numbered from the first frame of any of them (tick 0 then), so the
    agents share a tick only if they shared the swarm clock (`clock.epoch`); the radio a unit
    disk of unlimited range (a recording has no positions); no truth."""
    from swarmloc.experiment.scenario import SCENARIO_VERSION, parse

    cfgs = [m.get("config") for m in metas]
    if any(not isinstance(c, dict) for c in cfgs):
        raise RecordingError("an agent's recording without its configuration (metadata `config`)")
    ids = [c["id"] for c in cfgs]
    if len(set(ids)) != len(ids):
        raise RecordingError(f"two recordings of the same agent: ids {ids}")
    runs = [load(p) for p in paths]
    for cfg, run in zip(cfgs, runs):
        if not run.ticks:
            raise RecordingError(f"agent {cfg['id']}'s recording holds no sensor frame")
    k0 = min(r.ticks[0] for r in runs)
    last = max(r.ticks[-1] for r in runs)
    gaps = [(r.t[b] - r.t[a]) / (b - a) for r in runs for a, b in zip(r.ticks, r.ticks[1:])]
    dt = float(np.median(gaps)) if gaps else 0.1
    first = cfgs[0]
    agents = [{"id": c["id"], "model": c["model"], "start": c["prior"]["position"],
               "heading": c["prior"].get("heading") or 0.0} for c in cfgs]
    data = {
        "version": SCENARIO_VERSION, "name": "rerun-agents", "description": "agents' own recordings played again",
        "clock": {"dt": dt, "duration": max(1, last - k0) * dt},
        "world": {"source": "mcap", "path": json.dumps([str(p) for p in paths]), "agents": agents,
                  "landmarks": first.get("landmarks", [])},
        "radio": {"model": "unit-disk", "range_m": math.inf},
        "estimation": {"initial_std": first["prior"]["std"], "initial_heading_std": first["prior"]["heading_std"],
                       "initial_error": False, "gate": first.get("gate"),
                       "gate_open_after": first.get("gate_open_after", 10)},
        "estimator": {"name": estimator} if estimator is not None else first["estimator"],
        "references": [],
    }
    return parse(data, f"rerun of {', '.join(map(str, paths))}")


def load_world(path: str) -> tuple[RecordedRun, dict]:
    """What McapWorld plays: one netsim recording, or agents' own recordings (world.path a JSON
    list of files) merged, their ticks shifted so the first frame of any is tick 0. Returns the
    run and the shift {"k0": ..., "t0": ...}."""
    if not path.startswith("["):
        return load(Path(path)), {"k0": 0, "t0": 0.0}
    runs = [load(Path(p)) for p in json.loads(path)]
    k0 = min(r.ticks[0] for r in runs)
    t0 = min(r.t[r.ticks[0]] for r in runs)
    merged = RecordedRun({"writer": "agents"})
    for r in runs:
        for k, frames in r.sensors.items():
            for a, f in frames.items():
                f = replace(f, k=k - k0, t=f.t - t0)
                merged.sensors.setdefault(k - k0, {})[a] = f
                merged.t.setdefault(k - k0, f.t)
        merged.estimates += r.estimates
        merged.truncated |= r.truncated
    merged.ticks = sorted(merged.sensors)
    return merged, {"k0": k0, "t0": t0}
