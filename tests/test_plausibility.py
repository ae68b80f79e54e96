"""swarmloc.filters.plausibility and UKF-DCL's use of it, without I/O (issue 26, finding 7): a
neighbour's frame with wrong numbers is refused, counted by reason, and leaves the state alone."""

import numpy as np
import pytest
from helpers import in_process

from swarmloc.experiment import scenario as S
from swarmloc.filters import plausibility as pl

L = pl.LIMITS


def test_innovation_within_the_bound_passes_and_beyond_it_is_refused():
    S2 = np.diag([4.0, 1.0])
    assert pl.innovation(np.array([2.0 * 99, 0.0]), S2) is None  # 99 sigma
    assert pl.innovation(np.array([2.0 * 101, 0.0]), S2) == "implausible-innovation"
    assert pl.innovation(np.array([np.nan, 0.0]), S2) == "implausible-numbers"
    assert pl.innovation(np.array([1.0, 0.0]), np.diag([1.0, -1.0])) == "implausible-numbers"  # S indefinite
    assert L.nis_limit(1) == L.max_sigma**2 and L.nis_limit(1000) > 1000  # chi-square for many dof


def test_information_bounded_by_the_innovation_covariance():
    Y = np.array([[1.0], [2.0]])
    Pz = Y.T @ Y + 0.5
    assert pl.information(Y, Pz) is None
    assert pl.information(10 * Y, Pz) == "implausible-information"  # would shrink P below zero
    assert pl.information(Y, Y.T @ Y) is None  # exactly at the bound: a noise-free measurement
    assert pl.update(np.array([0.1]), Pz, 10 * Y) == "implausible-information"
    assert pl.update(np.array([1e11]), Pz, Y) == "implausible-innovation"


def test_posterior_psd_exactly_when_the_information_check_passes():
    rng = np.random.default_rng(1)
    for _ in range(200):
        A = rng.normal(size=(4, 4))
        P = A @ A.T + 0.1 * np.eye(4)
        Lc = np.linalg.cholesky(P)
        Y = rng.normal(size=(4, 1)) * rng.choice([0.3, 3.0])
        Pz = np.array([[rng.uniform(0.1, 10.0)]])
        Pxz = Lc @ Y
        post = P - Pxz @ np.linalg.solve(Pz, Pxz.T)
        assert (pl.information(Y, Pz) is None) == (np.linalg.eigvalsh(post).min() >= -1e-9 * np.abs(P).max())


def test_gain_covariance_and_information_matrix_checks():
    K = np.array([[0.3], [0.1]])
    assert pl.gain(K * (1 + 1e-9), K) is None
    assert pl.gain(K * 100, K) == "implausible-gain"
    assert pl.gain(np.full_like(K, np.inf), K) == "implausible-numbers"
    assert pl.covariance(np.eye(2)) is None
    assert pl.covariance(np.array([[1.0, 2.0], [2.0, 1.0]])) == "implausible-covariance"  # indefinite
    assert pl.covariance(np.array([[1.0, 0.5], [0.0, 1.0]])) == "implausible-covariance"  # asymmetric
    assert pl.information_matrix(np.zeros((2, 2))) is None  # no information is information
    assert pl.information_matrix(-np.eye(2)) == "implausible-information"
    assert pl.shift(np.array([3.0, 0.0]), np.eye(2)) is None
    assert pl.shift(np.array([300.0, 0.0]), np.eye(2)) == "implausible-shift"


@pytest.fixture(scope="module")
def wang2019_commits():
    """Every commit agent 2 made in a short wang2019 run, and the nodes at its end."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 10.0})
    _, nodes, _ = in_process(sc)
    return [c for c in nodes[2].log if c.key[0] == 2 and c.gains], nodes


def _forged_at(nodes, commit, **changes):
    """`commit`, changed, as the next commit of its measurer, handed to node 1 in its tick."""
    import msgspec

    node = nodes[1]
    forged = msgspec.structs.replace(commit, k=node.k, epoch=node.epoch, seq=node.version.get(2, 0) + 1,
                                     version=dict(node.version), participants=sorted(commit.gains),
                                     parent={j: 2 for j in commit.gains if j != 2}, **changes)
    return node, forged


@pytest.mark.parametrize("lie, reason", [("yn", "implausible-innovation"), ("gains", "implausible-gain"),
                                         ("information", "implausible-information")])
def test_a_dcl_node_refuses_a_forged_commit_and_keeps_its_estimate(wang2019_commits, lie, reason):
    commits, nodes = wang2019_commits
    assert commits
    c = commits[-1]
    changes = {"yn": dict(Y=np.full_like(c.Y, 1e11), nu=np.full_like(c.nu, 1e11)),
               "gains": dict(gains={j: 100 * g for j, g in c.gains.items()}),
               "information": dict(Y=10 * c.Y)}[lie]
    node, forged = _forged_at(nodes, c, **changes)
    x, own = node.x.copy(), node.row[1].copy()
    node._on_commit(2, forged)
    assert node.drops[reason] == 1
    assert np.array_equal(node.x, x) and np.array_equal(node.row[1], own)
    assert np.linalg.eigvalsh(node.row[1]).min() > 0
