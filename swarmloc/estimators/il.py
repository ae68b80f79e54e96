"""Independent localization (IL): dead reckoning on odometry alone, the paper's baseline."""

from __future__ import annotations

from swarmloc.filters import kalman
from swarmloc.node import Node, Send, odometry_of


class IndependentNode(Node):
    algorithm = "il"

    def step(self, sensors) -> list[Send]:
        gap = self.missed_motion(sensors)
        if gap is not None:
            self.P = self.P + gap
        x, F, Q = self.model.predict(self.x, odometry_of(sensors))
        self.x, self.P = kalman.predict(x, self.P, F, Q)
        self.k = sensors.k
        return []
