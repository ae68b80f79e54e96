"""An agent's node travels as a NodeSpec (plain JSON): what `swarmloc run` writes for each agent
and `python -m agents.daemon --spec` builds, without a scenario, pydantic or a CLI framework."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from swarmloc.estimators import REGISTRY
from swarmloc.experiment import scenario as S
from swarmloc.node import NodeSpec

CASES = [("wang2019", "ukf-dcl", {}), ("wang2019", "ukf-dcl", {"max_chain": 3}), ("wang2019", "il", {}),
         ("goel-dist", "ekf", {}), ("goel-dist", "ekf-ci", {"criterion": "det"}), ("goel-dist", "ekf-naive", {}),
         ("goel2node", "ekf-centre", {"wait": 0.02})]


@pytest.mark.parametrize("name,estimator,params", CASES, ids=lambda c: str(c))
def test_every_node_survives_its_spec_file(name, estimator, params):
    sc = S.load(name)
    info = REGISTRY[estimator]
    settings = info.settings(params)
    for aid in sc.agent_ids:
        direct = info.make_node(sc, aid, settings)
        spec = NodeSpec.loads(info.node_spec(sc, aid, settings).dumps())
        built = spec.build()
        assert type(built) is type(direct) and built.id == aid and built.algorithm == direct.algorithm
        a, b = built.estimate(), direct.estimate()
        assert np.array_equal(a.mean, b.mean) and np.array_equal(a.cov, b.cov)  # floats round-trip exactly
        for attr in ("max_chain", "criterion", "centre", "wait", "roster"):
            assert getattr(built, attr, None) == getattr(direct, attr, None), attr
        if hasattr(direct, "filter"):
            assert built.filter.imu == direct.filter.imu


def test_a_spec_names_only_swarmloc_classes():
    with pytest.raises(ValueError, match="not a swarmloc class"):
        NodeSpec.loads(json.dumps({"factory": "os:system", "kwargs": {"command": "true"}}))
    with pytest.raises(ValueError, match="unknown value"):
        NodeSpec.loads(json.dumps({"factory": "swarmloc.estimators.il:IndependentNode",
                                   "kwargs": {"aid": 1, "x0": {"dataclass": "os:Popen", "fields": {}}}})).build()


def test_the_agent_process_imports_no_scenario_tooling():
    code = ("import sys, agents.daemon, swarmloc.estimators.ukf.dcl, swarmloc.estimators.ekf.ci, "
            "swarmloc.estimators.ekf.centre, swarmloc.estimators.il, swarmloc.estimators.ctl.csl_ctl; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'pydantic', 'typer', 'yaml', 'rich', 'scipy', "
            "'matplotlib', 'swarmloc.experiment.scenario'}), 'swarmloc.experiment.scenario' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[] False", out


def test_daemon_entry_refuses_a_bad_spec(tmp_path):
    bad = tmp_path / "n.json"
    bad.write_text(NodeSpec.of(type(REGISTRY["il"].make_node(S.load("wang2019"), 2)), aid=2, x0=np.zeros(2),
                               P0=np.eye(2)).dumps())
    p = subprocess.run([sys.executable, "-m", "agents.daemon", "--id", "1", "--spec", str(bad), "--connect",
                        "tcp/127.0.0.1:9"], capture_output=True, text=True, timeout=30)
    assert p.returncode == 2 and "agent 2's node, not agent 1's" in p.stderr
    bad.write_text("{not json")
    p = subprocess.run([sys.executable, "-m", "agents.daemon", "--id", "1", "--spec", str(bad), "--connect",
                        "tcp/127.0.0.1:9"], capture_output=True, text=True, timeout=30)
    assert p.returncode == 2 and "--spec" in p.stderr


def test_swarmloc_imports_neither_agents_nor_netsim():
    """The import directions of docs/design.md: agents -> swarmloc and netsim -> swarmloc only."""
    import re

    root = Path(__file__).resolve().parent.parent
    pattern = re.compile(r"^\s*(from|import)\s+(agents|netsim)\b", re.M)
    offenders = [str(p.relative_to(root)) for p in sorted((root / "swarmloc").rglob("*.py")) if pattern.search(p.read_text())]
    assert offenders == []
    offenders = [str(p.relative_to(root)) for p in sorted((root / "agents").rglob("*.py"))
                 if re.search(r"^\s*(from|import)\s+netsim\b", p.read_text(), re.M)]
    assert offenders == []
