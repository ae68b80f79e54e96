"""The docs keep their promises: every link resolves inside the repository, and what
docs/run-format.md tells an outside reader is enough to rebuild a run's reference."""

import re
from pathlib import Path

import numpy as np
import pytest
from helpers import in_process

from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.experiment import scenario as S
from swarmloc.experiment.results import compute_references, frames_from_arrays
from swarmloc.experiment.rundir import write_run
from swarmloc.wire.messages import Sensors

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def anchors(page: Path) -> set[str]:
    """GitHub-style heading anchors of a Markdown page."""
    out = set()
    for line in page.read_text().splitlines():
        if line.startswith("#"):
            text = line.lstrip("#").strip().lower()
            out.add(re.sub(r"[^\w\- ]", "", text).replace(" ", "-"))
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_link_resolves_inside_the_repository(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # code blocks hold commands, not links
    for m in LINK.finditer(text):
        target = m.group(1) or m.group(2)
        assert not re.match(r"^[a-z]+://", target), f"{page.name}: {target} leaves the repository"
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.is_relative_to(ROOT) and dest.exists(), f"{page.name}: {target} does not exist"
        if anchor and dest.suffix == ".md":
            assert anchor in anchors(dest), f"{page.name}: no heading #{anchor} in {dest.name}"
    assert "../shared" not in page.read_text()


@pytest.mark.slow
def test_ukf_ccl_rebuilt_from_sensors_npz_in_the_documented_order(tmp_path):
    """docs/run-format.md: a tick's ranges apply in (m, n, q) order, a stable sort of the
    rows by tick, m, n. Following it reproduces the run's ukf-ccl; file order does not."""
    sc = S.load("random7").with_overrides(**{"clock.duration": 30.0})
    record, _, _ = in_process(sc)
    compute_references(sc, record, ["ukf-ccl"])
    write_run(tmp_path, sc, record, ["ukf-dcl", "ukf-ccl"], plots=False)
    s = dict(np.load(tmp_path / "sensors.npz", allow_pickle=False))
    reference = np.load(tmp_path / "estimates" / "ukf-ccl.npz")["mean"]
    documented = np.lexsort((np.arange(s["range_k"].size), s["range_n"], s["range_m"], s["range_k"]))

    def rebuild(order):
        ccl = CentralizedUKF({a: sc.prior(a)[0] for a in sc.agent_ids}, sc.prior(sc.agent_ids[0])[1],
                             spread=sc.estimation.spread)
        means = []
        for frames in frames_from_arrays(s):
            ccl.step({a: Sensors(f.k, f.t, f.odometry, [], f.gnss) for a, f in frames.items()})  # time update only
            k = next(iter(frames.values())).k
            for j in order[s["range_k"][order] == k]:
                m, n = int(s["range_m"][j]), int(s["range_n"][j])
                if m != n:
                    ccl.update(m, n, np.array([s["range_z"][j]]), np.array([[s["range_std"][j] ** 2]]))
            means.append(np.stack([ccl.x[ccl.block(a)] for a in sc.agent_ids]))
        return np.stack(means)

    assert np.abs(rebuild(documented) - reference).max() < 1e-9
    assert np.abs(rebuild(np.arange(s["range_k"].size)) - reference).max() > 1e-6
