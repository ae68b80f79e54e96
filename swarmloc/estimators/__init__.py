"""Estimators, and the one registry every part of swarmloc reads them from.

An estimator is either run by the agent processes (a sans-I/O `Node` per agent) or computed
offline from the recorded sensor stream as a reference (or both). The CLI's summary and its
`--estimator` choices, the scenario's validation, the run directory, the metrics and the plots
all take names, labels, colours and supported models from `REGISTRY`; adding an estimator is
one entry here plus its own module.

Factories are named by "module:attribute" and imported on first use, so reading the registry
(the CLI's help, scenario validation) does not import every estimator's maths.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

from swarmloc import resolve

PLANAR = ("planar-speed-heading",)
POSE = ("planar-pose",)  # heading in the state: F is not the identity (UKF-DCL: core coordinates)
UAS = ("uas-ins",)
VEHICLES = ("quadrotor", "ground-robot")  # Oliveros & Ashrafiuon 2023: driven by their actuator commands


@dataclass(frozen=True)
class EstimatorInfo:
    """What the rest of swarmloc knows about one estimator.

    node: "module:callable", callable(scenario, aid, settings) -> swarmloc.node.NodeSpec, for an
    estimator the agents run (a ground station gets an idle node unless `models` names
    "ground-station"), or a mapping from motion model to such a callable, for an estimator whose
    families implement it per model (ekf-ci on UAS, planar-pose robots and vehicles). The agent
    process builds its node from that spec alone.
    reference: whether it can be computed offline from a run's sensor stream; batch:
    "module:callable", callable(scenario, ids, settings) -> an object with step(frames) and
    estimate(aid), for a reference that is not a per-agent filter (a per-agent one is computed
    by running its nodes offline one by one). settings_path: "module:PydanticModel" validating
    the scenario's `estimator.params` (in swarmloc.estimators.settings)."""

    name: str
    label: str
    description: str
    models: tuple[str, ...]
    color: str
    node: str | Mapping[str, str] | None = None
    reference: bool = False
    batch: str | None = None
    settings_path: str | None = None
    paper: str = ""
    # What a scenario must have for this estimator to be a default reference there, and to be
    # run by its agents: "targets" (it localizes targets), "gnss" (it needs GNSS fixes).
    requires: tuple[str, ...] = ()
    # What a summary compares against: "baseline", no cooperation or a naive one (what
    # cooperating must beat); "reference", the centralized filter over the joint state (what a
    # distributed one should match); "" for the others.
    role: str = ""

    @property
    def runs_on_agents(self) -> bool:
        return self.node is not None

    def settings(self, params: dict | None = None):
        """The validated parameters, a pydantic model (ValueError naming the bad field otherwise)."""
        from pydantic import ValidationError

        from swarmloc.errors import readable
        from swarmloc.estimators.settings import NoSettings

        model = resolve(self.settings_path) if self.settings_path else NoSettings
        try:
            return model.model_validate(params or {})
        except ValidationError as exc:
            bad = "; ".join(f"{'.'.join(map(str, e['loc']))}: {readable(e)}" for e in exc.errors())
            raise ValueError(f"estimator {self.name} params: {bad}") from None

    def node_spec(self, scenario, aid: int, settings=None):
        """Agent aid's node as plain values (swarmloc.node.NodeSpec): what its process builds."""
        from swarmloc.node import Idle, NodeSpec

        if self.node is None:
            raise ValueError(f"{self.name} is a reference, not run by agents")
        agent = scenario.agent(aid)
        if not agent.localized and agent.model not in self.models:
            return NodeSpec.of(Idle, aid=aid, algorithm=self.name)
        factory = self.node if isinstance(self.node, str) else self.node.get(agent.model)
        if factory is None:
            raise ValueError(f"{self.name} runs on {', '.join(self.node)} platforms; agent {aid} is {agent.model}")
        return resolve(factory)(scenario, aid, settings if settings is not None else self.settings())

    def make_node(self, scenario, aid: int, settings=None):
        return self.node_spec(scenario, aid, settings).build()

    def make_reference(self, scenario, ids: list[int], settings=None):
        settings = settings if settings is not None else self.settings()
        if self.batch is not None:
            return resolve(self.batch)(scenario, ids, settings)
        return PerNodeReference({a: self.make_node(scenario, a, settings) for a in ids})


class PerNodeReference:
    """A per-agent filter computed offline: each node alone on its own sensor frames."""

    def __init__(self, nodes: dict):
        self.nodes = nodes

    def step(self, frames: dict) -> None:
        for a, node in self.nodes.items():
            node.step(frames[a])

    def estimate(self, aid: int):
        from swarmloc.node import estimate_of

        return estimate_of(self.nodes[aid])


@dataclass
class Registry:
    entries: dict[str, EstimatorInfo] = field(default_factory=dict)

    def add(self, info: EstimatorInfo) -> None:
        if info.name in self.entries:
            raise ValueError(f"estimator {info.name} registered twice")
        self.entries[info.name] = info

    def __getitem__(self, name: str) -> EstimatorInfo:
        return self.entries[name]

    def __contains__(self, name: str) -> bool:
        return name in self.entries

    def __iter__(self):
        return iter(self.entries.values())

    def get(self, name: str) -> EstimatorInfo | None:
        return self.entries.get(name)

    def running(self) -> list[str]:
        """Names the agents can run."""
        return [e.name for e in self if e.runs_on_agents]

    def references(self) -> list[str]:
        """Names computable offline from a run's sensor stream."""
        return [e.name for e in self if e.reference]

    def label(self, name: str) -> str:
        e = self.get(name)
        return e.label if e else name

    def color(self, name: str) -> str:
        e = self.get(name)
        return e.color if e else "0.5"

    def order(self, names: Iterable[str]) -> list[str]:
        """Names in registry order (the order of summaries and legends)."""
        names = set(names)
        return [e.name for e in self if e.name in names] + sorted(n for n in names if n not in self.entries)


REGISTRY = Registry()
for _info in (
    EstimatorInfo("il", "IL", "dead reckoning on odometry alone, each robot by itself", PLANAR + POSE, "tab:gray",
                  node="swarmloc.estimators.il:IndependentNode.spec", reference=True,
                  paper="Wang et al. 2019 (baseline)", role="baseline"),
    EstimatorInfo("ukf-dcl", "UKF-DCL", "distributed UKF over serial chains of the robots a measurement correlates",
                  PLANAR + POSE, "tab:blue", node="swarmloc.estimators.ukf.dcl:UkfDclNode.spec",
                  settings_path="swarmloc.estimators.settings:DclSettings", paper="Wang et al. 2019"),
    EstimatorInfo("rdl", "RDL", "recursive decentralized localization: a range updates the two robots that took it "
                  "and no one else, each holding one factor of every cross-covariance", PLANAR + POSE, "tab:pink",
                  node="swarmloc.estimators.rdl.node:RdlNode.spec",
                  settings_path="swarmloc.estimators.settings:RdlSettings", paper="Luft et al. 2018"),
    EstimatorInfo("ukf-ccl", "UKF-CCL", "centralized UKF over the joint state of the swarm", PLANAR + POSE, "tab:orange",
                  reference=True, batch="swarmloc.estimators.ukf.ccl:CentralizedUKF.from_scenario",
                  settings_path="swarmloc.estimators.settings:CclSettings",
                  paper="Wang et al. 2019 (gold standard)", role="reference"),
    EstimatorInfo("csl-ctl", "CSL-CTL", "joint UKF of the swarm re-estimated with the targets by majorization each "
                  "tick; every agent runs it on the frames all agents broadcast", PLANAR + POSE, "tab:green",
                  node="swarmloc.estimators.ctl.csl_ctl:CslCtlNode.spec", reference=True,
                  batch="swarmloc.estimators.ctl.csl_ctl:JointCslCtl.from_scenario",
                  settings_path="swarmloc.estimators.settings:CtlSettings", paper="Wang et al. 2022", requires=("targets",)),
    EstimatorInfo("il-ctl", "IL-CTL", "dead reckoning alone, then targets by least squares from the positions "
                  "agents broadcast, taken as exact", PLANAR + POSE, "tab:red",
                  node="swarmloc.estimators.ctl.csl_ctl:IlCtlNode.spec", reference=True,
                  batch="swarmloc.estimators.ctl.csl_ctl:il_ctl_reference",
                  settings_path="swarmloc.estimators.settings:CtlSettings", paper="Wang et al. 2022 (baseline)",
                  requires=("targets",), role="baseline"),
    EstimatorInfo("dnbp", "dNBP", "nonparametric belief propagation: beliefs as weighted samples, agents without "
                  "GNSS fuse rings around their neighbours' beliefs under the paper's message schedule", PLANAR,
                  "tab:purple", node="swarmloc.estimators.nbp.dnbp:DnbpNode.spec",
                  settings_path="swarmloc.estimators.settings:DnbpSettings", paper="Wan et al. 2014"),
    EstimatorInfo("ls", "LS", "GNSS when there is a fix; without, multilateration from the agents with a fix it "
                  "ranged (at least 3), else dead reckoning", PLANAR, "tab:brown", reference=True,
                  batch="swarmloc.estimators.nbp.dnbp:LeastSquaresReference.from_scenario",
                  paper="Wan et al. 2014 (baseline)", requires=("gnss",), role="baseline"),
    EstimatorInfo("ekf", "EKF alone", "each platform's own EKF, nothing shared: INS/GNSS on a UAS, odometry and "
                  "landmarks on a planar-pose robot", UAS + POSE, "tab:cyan",
                  node={"uas-ins": "swarmloc.estimators.ekf.local:EkfNode.spec",
                        "planar-pose": "swarmloc.estimators.ekf.pose:PoseEkfNode.spec"}, reference=True,
                  paper="Goel et al. 2016 (no sharing)", role="baseline"),
    EstimatorInfo("ekf-ci", "EKF-CI", "each platform's EKF fuses its neighbours' estimates through relative "
                  "measurements with covariance intersection", UAS + POSE + VEHICLES, "tab:green",
                  node={"uas-ins": "swarmloc.estimators.ekf.ci:CiNode.spec",
                        "planar-pose": "swarmloc.estimators.ekf.pose:PoseCiNode.spec",
                        "quadrotor": "swarmloc.estimators.vehicles.cl:CiVehicleNode.spec",
                        "ground-robot": "swarmloc.estimators.vehicles.cl:CiVehicleNode.spec"},
                  settings_path="swarmloc.estimators.settings:CiSettings", paper="Goel et al. 2016, section 4"),
    EstimatorInfo("ekf-naive", "EKF naive", "as EKF-CI, but neighbours' estimates are fused as if independent",
                  UAS, "tab:red", node="swarmloc.estimators.ekf.ci:NaiveNode.spec",
                  settings_path="swarmloc.estimators.settings:CiSettings", paper="baseline for Goel et al. 2016",
                  role="baseline"),
    EstimatorInfo("ekf-centre", "EKF centre", "a fusion-centre process runs the joint EKF of the swarm over the radio; "
                  "UAS fall back to their own EKF when it is out of reach", UAS + ("ground-station",), "tab:purple",
                  node="swarmloc.estimators.ekf.centre:node_spec",
                  settings_path="swarmloc.estimators.settings:CentreSettings", paper="Goel et al. 2016, section 3"),
    EstimatorInfo("ekf-cl", "EKF-CL", "quadrotors and ground robots: a fusion-centre process runs the joint EKF of "
                  "the vehicles over the radio (relative positions in body frames); a vehicle falls back to its own "
                  "EKF when the answer does not come", VEHICLES + ("ground-station",), "tab:purple",
                  node="swarmloc.estimators.vehicles.cl:node_spec",
                  settings_path="swarmloc.estimators.settings:CentreSettings", paper="Oliveros & Ashrafiuon 2023"),
    EstimatorInfo("ekf-local", "EKF, no CL", "quadrotors and ground robots: each vehicle's own EKF; a relative "
                  "position is fused against the target's broadcast estimate, correlations ignored", VEHICLES,
                  "tab:red", node="swarmloc.estimators.vehicles.cl:LocalNode.spec",
                  paper="baseline for Oliveros & Ashrafiuon 2023 (CL without cross-covariances)", role="baseline"),
    EstimatorInfo("raw", "raw, no CL", "quadrotors and ground robots: each controller fed the raw measurements of "
                  "its pose (GPS, else a relative position from the target's raw position, else its own EKF; the "
                  "IMU's orientation), its own EKF for velocities and rates", VEHICLES, "tab:brown",
                  node="swarmloc.estimators.vehicles.cl:RawNode.spec", paper="Oliveros & Ashrafiuon 2023 (without CL)",
                  role="baseline"),
    EstimatorInfo("ekf-ccl", "EKF-CCL", "centralized EKF over the joint state of the swarm, offline", UAS + POSE,
                  "tab:olive", reference=True, batch="swarmloc.estimators.ekf.ccl:CentralizedEkf.from_scenario",
                  settings_path="swarmloc.estimators.settings:CclSettings",
                  paper="Goel et al. 2016, section 3", role="reference"),
):
    REGISTRY.add(_info)


def make_nodes(name: str, scenario, ids: Iterable[int] | None = None, params: dict | None = None) -> dict:
    """One node per agent (ground stations included) for the estimator `name`."""
    info = REGISTRY[name]
    settings = info.settings(scenario.estimator.params if params is None and scenario.estimator.name == name else params)
    return {a: info.make_node(scenario, a, settings) for a in (ids if ids is not None else scenario.agent_ids)}


__all__ = ["REGISTRY", "EstimatorInfo", "Registry", "make_nodes", "PerNodeReference"]
