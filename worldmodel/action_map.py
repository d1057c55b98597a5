"""How the actor's output ``u`` in [-1, 1]^2 becomes the simulator's action [steer, throttle/brake].

The paper's parameterisation is the identity (``steer=wheel``, ``anchor=none``). Two options change what the
actor's numbers mean, and so what an untrained actor and its exploration noise do:

* ``anchor=brake``: the pedal is a residual on full braking, ``pedal = clip(-1 + 2 u_pedal, -1, 1)``, so
  ``u = 0`` is straight-line braking exactly (with the actor's last layer initialised to zero, the untrained
  policy *is* the baseline), ``u_pedal = 0.5`` coasts and ``u_pedal = 1`` is full throttle.
* ``steer=grip``: ``u_steer`` is the fraction of the grip-limited lateral acceleration mu g asked for at the
  current speed v: the wheel angle is ``atan(L mu g |u| / v^2)``, capped by the steering limit. At 30 m/s the
  whole useful range (steer ~ 0.05 in wheel units) becomes u in [-1, 1], and Gaussian noise on u is noise on
  lateral acceleration, whatever the speed.

The mapping belongs to the environment as the agent sees it (``agent_obs.WorldModelView`` and ``LearnedPolicy``
apply it): the critic learns Q(s, u) and the replay buffer stores u, while the LSTM is fed the simulator's action,
as in its training data. An agent's checkpoint records its mapping, so evaluation acts with the same one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from envs.vehicle import G, VehicleParams

ANCHORS = ("none", "brake")
STEERS = ("wheel", "grip")


@dataclass(frozen=True)
class ActionMap:
    anchor: str = "none"
    steer: str = "wheel"
    params: VehicleParams = VehicleParams()

    def __post_init__(self):
        if self.anchor not in ANCHORS:
            raise ValueError(f"action anchor {self.anchor!r}: use one of {', '.join(ANCHORS)}")
        if self.steer not in STEERS:
            raise ValueError(f"action steer {self.steer!r}: use one of {', '.join(STEERS)}")

    @property
    def identity(self) -> bool:
        return self.anchor == "none" and self.steer == "wheel"

    def to_env(self, u, speed: float) -> np.ndarray:
        """The simulator's action for actor output ``u`` at ego speed ``speed`` (m/s)."""
        u = np.clip(np.asarray(u, dtype=np.float32).reshape(2), -1.0, 1.0)
        if self.identity:
            return u
        steer, pedal = float(u[0]), float(u[1])
        if self.anchor == "brake":
            pedal = min(1.0, max(-1.0, -1.0 + 2.0 * pedal))
        if self.steer == "grip":
            steer = self.grip_steer(steer, speed)
        return np.array([steer, pedal], dtype=np.float32)

    def grip_steer(self, fraction: float, speed: float) -> float:
        """Wheel-unit steer asking for ``fraction`` of mu g lateral acceleration at ``speed`` (kinematic model)."""
        p = self.params
        v2 = max(float(speed), 0.1) ** 2
        wheel = math.atan(p.wheelbase * p.mu * G * abs(fraction) / v2)
        return math.copysign(min(1.0, wheel / p.max_steer), fraction)

    def from_env(self, action, speed: float) -> np.ndarray:
        """The actor output ``u`` that asks for the simulator's ``action`` at ``speed`` (the inverse of
        ``to_env`` where it has one): how a demonstration's actions become the actor's targets. A wheel angle
        beyond what grip allows at this speed becomes |u| = 1, which asks for all of it."""
        action = np.clip(np.asarray(action, dtype=np.float32).reshape(2), -1.0, 1.0)
        if self.identity:
            return action
        steer, pedal = float(action[0]), float(action[1])
        if self.anchor == "brake":
            pedal = (pedal + 1.0) / 2.0
        if self.steer == "grip":
            p = self.params
            v2 = max(float(speed), 0.1) ** 2
            fraction = v2 * math.tan(abs(steer) * p.max_steer) / (p.wheelbase * p.mu * G)
            steer = math.copysign(min(1.0, fraction), steer)
        return np.array([steer, pedal], dtype=np.float32)

    def to_dict(self) -> dict:
        return {"anchor": self.anchor, "steer": self.steer, "params": asdict(self.params)}

    @classmethod
    def from_dict(cls, d: dict | None) -> ActionMap:
        """From a checkpoint's record; an agent saved before the option existed used the identity."""
        if not d:
            return cls()
        return cls(d["anchor"], d["steer"], VehicleParams(**d["params"]))
