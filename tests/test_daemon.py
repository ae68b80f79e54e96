"""The agent daemon's restart path, without Zenoh: what a node resumes from."""

import numpy as np

from agents.daemon import AgentConfig, AgentDaemon
from swarmloc.experiment import scenario as S
from swarmloc.experiment.runner import make_nodes
from swarmloc.wire.messages import OdometryMsg, Sensors


def restarted(tmp_path, content: bytes | None):
    sc = S.load("wang2019")
    node = make_nodes("ukf-dcl", sc, [3])[3]
    state = tmp_path / "3.state.npy"
    if content is not None:
        state.write_bytes(content)
    daemon = AgentDaemon(node, AgentConfig(state_file=state))
    return daemon.resume(), node, sc.prior(3)


def frame(k, dt=0.5, speed=1.0, speed_std=0.5):
    return Sensors(k, k * dt, OdometryMsg(dt, speed, 0.0, speed_std, 0.0), [])


def test_unusable_checkpoint_resumes_from_the_prior_as_an_orphan_with_the_missed_ticks(tmp_path):
    resumed, node, (x0, P0) = restarted(tmp_path, b"not a numpy file")
    assert not resumed
    assert node.orphan and node.k == -1 and np.array_equal(node.x, x0)
    node.step(frame(50))
    reach = 50 * 0.5 * (1.0 + 3 * 0.5)  # ticks 0..49 missed, at the reported speed + 3 std
    assert node.row[3][0, 0] >= P0[0, 0] + reach**2


def test_checkpoint_resumes_its_tick_mean_and_covariance(tmp_path):
    import io

    buf = io.BytesIO()
    np.save(buf, np.concatenate([[40], [5.0, 6.0], np.eye(2).ravel() * 4.0]))
    resumed, node, _ = restarted(tmp_path, buf.getvalue())
    assert resumed and node.orphan and node.k == 40 and np.array_equal(node.x, [5.0, 6.0])
    node.step(frame(41))  # the next tick: nothing missed, only the time update
    assert node.row[3][0, 0] < 4.0 + 1.0


def test_no_checkpoint_is_a_first_start(tmp_path):
    resumed, node, _ = restarted(tmp_path, None)
    assert not resumed and not node.orphan and node.k == -1
