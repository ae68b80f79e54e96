"""Draw a run.mcap's scene at one moment, as Foxglove's 3D panel receives it, seen from above.

Foxglove's app is not available on an offline machine, so this reads what it would draw: the
last /scene and /scene/static messages (foxglove.SceneUpdate) at or before the moment, decoded
with the schemas stored in the file (mcap and mcap-protobuf-support, no swarmloc), and draws
their primitives with matplotlib as the 3D panel does from above: spheres (truth black, each
estimator in its colour), the 95 % ellipses (flat elliptic cylinders), links (line segments in
their per-point colours), landmarks (cubes) and texts; under the plot, the /faults log entries up
to that moment.

Usage: python benchmarks/render_scene.py RUN/run.mcap --t 25 --out docs/img/scene.png
"""

from __future__ import annotations

import argparse
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Ellipse, Rectangle  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_protobuf.decoder import DecoderFactory  # noqa: E402


def _yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def _rgba(c):
    return (c.r, c.g, c.b, c.a)


def scene_at(path: str, t: float):
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        start = reader.get_summary().statistics.message_start_time
        until = start + int(t * 1e9)
        latest, faults = {}, []
        for _, channel, message, decoded in reader.iter_decoded_messages(
                topics=["/scene", "/scene/static", "/faults"], ending_at=until):
            if channel.topic == "/faults":
                faults.append(decoded.message)
            else:
                latest[channel.topic] = decoded
    return latest, faults


def draw(path: str, t: float, out: str, title: str | None = None) -> None:
    latest, faults = scene_at(path, t)
    fig, ax = plt.subplots(figsize=(8, 7.2))
    for topic in ("/scene/static", "/scene"):
        update = latest.get(topic)
        if update is None:
            continue
        for e in update.entities:
            for ln in e.lines:
                pts = ln.points
                for i in range(0, len(pts) - 1, 2):
                    c = _rgba(ln.colors[i]) if ln.colors else _rgba(ln.color)
                    ax.plot([pts[i].x, pts[i + 1].x], [pts[i].y, pts[i + 1].y], color=c, lw=2, zorder=1)
            for cyl in e.cylinders:
                p = cyl.pose
                ax.add_patch(Ellipse((p.position.x, p.position.y), cyl.size.x, cyl.size.y,
                                     angle=math.degrees(_yaw(p.orientation)), facecolor=_rgba(cyl.color),
                                     edgecolor=_rgba(cyl.color)[:3], lw=0.8, zorder=2))
            for cube in e.cubes:
                p = cube.pose.position
                ax.add_patch(Rectangle((p.x - cube.size.x / 2, p.y - cube.size.y / 2), cube.size.x, cube.size.y,
                                       color=_rgba(cube.color), zorder=3))
            for s in e.spheres:
                p = s.pose.position
                ax.add_patch(Ellipse((p.x, p.y), s.size.x, s.size.y, color=_rgba(s.color), zorder=4))
            for tx in e.texts:
                p = tx.pose.position
                ax.annotate(tx.text, (p.x, p.y), color=_rgba(tx.color), fontsize=9, zorder=5,
                            ha="left" if e.id == "faults" else "center", va="bottom")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.08)
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.grid(alpha=0.3)
    ax.set_title(title or f"{path}: /scene at t = {t:g} s (what Foxglove's 3D panel draws, seen from above)",
                 fontsize=10)
    if faults:
        fig.text(0.02, 0.01, "/faults: " + "\n".join(faults[-4:]), fontsize=8, va="bottom", family="monospace")
        fig.subplots_adjust(bottom=0.12 + 0.02 * min(4, len(faults)))
    fig.savefig(out, dpi=110)
    print(f"{out}: {sum(len(u.entities) for u in latest.values())} entities, {len(faults)} fault entries up to {t:g} s")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("recording")
    p.add_argument("--t", type=float, required=True, help="seconds after the recording's first message")
    p.add_argument("--out", required=True)
    p.add_argument("--title", default=None)
    a = p.parse_args()
    draw(a.recording, a.t, a.out, a.title)


if __name__ == "__main__":
    main()
