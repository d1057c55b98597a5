"""Scripted policies. Each has ``reset(seed)`` and ``act(obs, info) -> np.ndarray([steer, pedal], float32)``.

They read the ego state from ``info`` (x, y, heading, speed), never from the env's internals, so they run
unchanged on a recorded or wrapped env.
"""

from __future__ import annotations

import math

import numpy as np

from .scene import EGO_LANE_Y
from .vehicle import VehicleParams


class ConstantAction:
    """The same action at every step (tests, and baselines such as holding speed)."""

    def __init__(self, action=(0.0, 0.0), name: str = "constant"):
        self.action = np.array(action, dtype=np.float32).reshape(2)
        self.name = name

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs, info) -> np.ndarray:
        return self.action


class StraightLineBraking:
    """The baseline: full brake from onset, wheel straight."""

    name = "braking"

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs, info) -> np.ndarray:
        return np.array([0.0, -1.0], dtype=np.float32)


class NoisyAutopilot:
    """Lane keeping with noise and sustained excursions: the data collector.

    Steering is pure pursuit towards a target lateral position (the lane centre; look-ahead grows with speed,
    which keeps it stable from 1 to 30 m/s); the pedal holds the onset speed. Gaussian noise goes on both
    channels. With probability ``excursion_rate`` per step (and ``onset_excursion_prob`` at the very first
    step, where the hazards are) a sustained excursion starts and lasts a duration drawn from ``excursion_s``:

    * ``brake``: a constant brake of 30-100 %;
    * ``lane_change``: pure pursuit towards another lateral position across the road (oncoming lane, kerb,
      sidewalk edge), the evasive manoeuvre a learned policy may use;
    * ``swerve``: a constant steering input of 30-100 % (``hard_swerve_share`` of the steering excursions),
      which often ends against a pole or a wall, so the world model also sees what that looks like.

    The mix covers the action space near hazards, not only gentle driving, without ending most episodes
    in a static crash.
    """

    name = "autopilot"

    def __init__(
        self,
        steer_noise: float = 0.15,
        throttle_noise: float = 0.15,
        excursion_rate: float = 0.03,
        excursion_s: tuple[float, float] = (0.4, 1.5),
        onset_excursion_prob: float = 0.5,
        hard_swerve_share: float = 0.2,
        dt: float = 1.0 / 15.0,
        params: VehicleParams = VehicleParams(),
    ):
        probs = (excursion_rate, onset_excursion_prob, hard_swerve_share)
        if min(steer_noise, throttle_noise) < 0 or not all(0.0 <= p <= 1.0 for p in probs):
            raise ValueError("autopilot noise levels must be >= 0 and its probabilities in [0, 1]")
        self.steer_noise, self.throttle_noise = steer_noise, throttle_noise
        self.excursion_rate, self.excursion_s = excursion_rate, tuple(excursion_s)
        self.onset_excursion_prob, self.hard_swerve_share = onset_excursion_prob, hard_swerve_share
        self.dt, self.params = dt, params
        self.reset(0)

    def reset(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)
        self.target_speed = None
        self.excursion_left = 0
        self.kind = None
        self.fixed = np.zeros(2)
        self.target_y = EGO_LANE_Y
        self.first = True

    def _start_excursion(self) -> None:
        rng = self.rng
        self.excursion_left = max(1, int(rng.uniform(*self.excursion_s) / self.dt))
        u = rng.random()
        if u < 0.4:
            self.kind, self.fixed = "brake", np.array([np.nan, -rng.uniform(0.3, 1.0)])
        elif u < 0.4 + 0.6 * (1.0 - self.hard_swerve_share):
            self.kind, self.target_y = "lane_change", EGO_LANE_Y + rng.uniform(-3.5, 5.0)
        else:
            self.kind = "swerve"
            self.fixed = np.array([rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.0), np.nan])

    def act(self, obs, info) -> np.ndarray:
        v = float(info["speed"])
        if self.target_speed is None:
            self.target_speed = v
        if self.excursion_left == 0:
            self.kind = None
            chance = self.onset_excursion_prob if self.first else self.excursion_rate
            if self.rng.random() < chance:
                self._start_excursion()
        self.first = False

        target_y = self.target_y if self.kind == "lane_change" else EGO_LANE_Y
        lookahead = max(6.0, (0.6 if self.kind == "lane_change" else 1.2) * v)
        alpha = math.atan2(target_y - float(info["y"]), lookahead) - float(info["heading"])
        delta = math.atan(2.0 * self.params.wheelbase * math.sin(alpha) / lookahead)
        steer = -delta / self.params.max_steer  # positive action steers right
        pedal = 0.5 * (self.target_speed - v)
        # Steering noise is a share of the grip-limited wheel angle at this speed: the same action noise
        # that is a gentle wobble at 5 m/s would saturate the tyres at 30 m/s.
        grip_steer = math.atan(self.params.mu * 9.81 * self.params.wheelbase / max(v, 1.0) ** 2)
        steer_sigma = self.steer_noise * min(1.0, grip_steer / self.params.max_steer)
        action = np.array([steer, pedal]) + self.rng.normal(0.0, [steer_sigma, self.throttle_noise])
        if self.excursion_left > 0:
            self.excursion_left -= 1
            if self.kind in ("brake", "swerve"):
                action = np.where(np.isnan(self.fixed), action, self.fixed)
            if self.kind == "brake":
                self.target_speed = min(self.target_speed, v)  # after braking, carry on at the lower speed
        return np.clip(action, -1.0, 1.0).astype(np.float32)
