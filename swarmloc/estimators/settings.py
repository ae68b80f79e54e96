"""The estimators' settings (scenario `estimator.params`), validated where the scenario is.

They live apart from the nodes on purpose: an agent process builds its node from a NodeSpec of
plain values (swarmloc.node), so it never imports pydantic, which costs an agent about 17 MB.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class NoSettings(BaseModel):
    """An estimator without parameters of its own."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class OdometryBiasSettings(BaseModel):
    """Per-robot odometry bias states on planar-pose robots (swarmloc.models.motion.PlanarPoseBias,
    docs/mrclam.md): one set of settings for every estimator that can carry them, so the distributed
    filter and its centralized reference run the same model."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    odometry_bias: bool = Field(False, description="planar-pose: augment each robot's pose with a scale factor on its "
                                "measured speed and a bias on its measured turn rate, both random walks; estimates "
                                "report the pose alone")
    speed_scale_walk: float = Field(1e-5, ge=0, description="random-walk intensity of the speed scale factor (1/s: "
                                    "its variance grows by this much per second)")
    turn_rate_bias_walk: float = Field(1e-6, ge=0, description="random-walk intensity of the turn-rate bias "
                                       "((rad/s)^2 per s)")
    speed_scale_std: float = Field(0.05, gt=0, description="prior std of the speed scale factor (0.05: 5 %)")
    turn_rate_bias_std: float = Field(0.02, gt=0, description="prior std of the turn-rate bias (rad/s)")


class DclSettings(OdometryBiasSettings):
    """UKF-DCL settings: bounded chains; on planar-pose robots, the odometry bias states of its
    centralized twin UKF-CCL (the same settings give the same filter)."""

    max_chain: int | None = Field(
        None, ge=2, description="the most platforms one chain visits, the measuring and the measured one included "
        "(bounded chains). The platforms a chain does not visit apply its commit as outsiders, and chains whose "
        "platforms are busy run at the same time instead of one after the other. null: every chain visits the "
        "whole connected swarm, one chain at a time, and the filter equals the centralized UKF")


class RdlSettings(BaseModel):
    """RDL settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    beacon_every: int = Field(
        1, ge=1, le=3, description="ticks between two beacons of a platform, staggered by id (every platform "
        "beacons in its first ticks). A beacon only says who is in reach: a neighbour stays known for 3 ticks after "
        "its last, so up to 3 loses no range on a lossless radio and cuts the swarm's deliveries (at 256 platforms "
        "a beacon to each of ~24 in reach is most of them); a lost beacon then counts for more")


class CiSettings(BaseModel):
    """EKF-CI (and naive fusion) settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    criterion: Literal["trace", "det"] = Field(
        "trace", description="what the CI weight omega minimises in the fused covariance: its trace (the paper's "
        "eq. 22, over the 16 states: m^2, (m/s)^2 and rad^2 added, position and clock dominate) or its determinant "
        "(unit-free)")


class CentreSettings(BaseModel):
    """Parameters of the fusion-centre estimator ("ekf-centre")."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    centre: int | None = Field(None, ge=0, description="agent id of the ground station that runs the fusion centre; "
                               "default: the scenario's only ground-station agent")
    wait: float = Field(0.05, ge=0, description="seconds the centre waits, from the first datum of a tick, for the "
                        "other UAS' data before it runs the tick with what it has")
    forget_after: int = Field(20, ge=1, description="ticks without data after which the centre stops waiting for a UAS "
                              "(a UAS without data in a tick leaves the joint state at once, and is taken back in from "
                              "its own estimate when its data come again)")


class CtlSettings(BaseModel):
    """CSL-CTL and IL-CTL settings (docs/csl-ctl.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    tol: float = Field(1e-9, ge=0, description="CSL-CTL: the majorization stops when one step lowers the stress by "
                       "less than tol times the stress")
    max_iter: int = Field(100, ge=1, description="CSL-CTL: iteration cap of one majorization")
    ut_noise: bool = Field(True, description="CSL-CTL: the unscented transform that gives the re-estimate's "
                           "covariance spans the target ranges' noise as well as the prior; false: the prior only "
                           "(the paper's 4N+1 sigma points), which leaves the ranges' noise out of the covariance")
    min_ranges: int = Field(3, ge=2, description="a target is first localized in a tick in which at least this many "
                            "agents range it")
    target_process_noise: float = Field(0.0, ge=0, description="random-walk intensity of a target's position "
                                        "(m^2/s): 0 for a static target")
    wait: float = Field(0.1, ge=0, description="seconds an agent waits, from its own frame, for the other agents' "
                        "shares of the tick before it runs the tick with what it has (real time; in lockstep the "
                        "tick runs when the shares are in, or at the next tick)")
    forget_after: int = Field(10, ge=1, description="ticks without a share after which an agent stops waiting for "
                              "another")


class DnbpSettings(BaseModel):
    """dNBP settings (docs/dnbp.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    M: int = Field(300, ge=10, le=1000, description="samples per belief and per message")
    iterations: int = Field(3, ge=1, le=255, description="most beliefs a fault agent sends in one time slice (each "
                            "new message after its first send refines and re-sends it)")
    quiet: float = Field(0.1, gt=0, description="seconds without a new message after which a fault agent below its "
                         "threshold lowers it (3 -> 2 -> 1); in lockstep this takes effect at the slice's end")
    ring_scale: float = Field(4.0, ge=0, description="kernel std of a ring message, in units of the ring's thickness "
                              "(range noise, the sender's kernel and the spacing of M samples around the ring); 0: "
                              "Silverman's rule over the ring's samples")
    thresholds: list[int] = Field([3, 2, 1], min_length=1, description="messages a fault agent needs before it sends, "
                                  "strictly decreasing, each >= 1 (the paper: 3, then 2, then 1)")

    @field_validator("thresholds")
    @classmethod
    def _decreasing(cls, v):
        if any(x < 1 for x in v) or any(a <= b for a, b in zip(v, v[1:])):
            raise ValueError("strictly decreasing integers >= 1")
        return v


class CclSettings(OdometryBiasSettings):
    """EKF-CCL and UKF-CCL settings: on planar-pose robots, per-robot odometry bias states."""
