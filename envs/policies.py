"""Scripted policies. Each has ``reset(seed)`` and ``act(obs, info) -> np.ndarray([steer, pedal], float32)``.

They read the ego state from ``info`` (x, y, heading, speed), never from the env's internals, so they run
unchanged on a recorded or wrapped env.
"""
from __future__ import annotations

import math

import numpy as np

from .scene import EGO_LANE_Y
from .vehicle import VehicleParams


class StraightLineBraking:
    """The baseline: full brake from onset, wheel straight."""

    name = "braking"

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs, info) -> np.ndarray:
        return np.array([0.0, -1.0], dtype=np.float32)


class NoisyAutopilot:
    """Lane keeping with noise and occasional sustained excursions: the data collector.

    Steering is pure pursuit towards the lane centre (look-ahead grows with speed, which keeps it stable
    from 1 to 30 m/s); the pedal holds the onset speed. Gaussian noise goes on both channels, and with
    probability ``excursion_rate`` per step a sustained hard brake or swerve starts and lasts a duration
    drawn from ``excursion_s``, so the data covers the whole action space, not only gentle driving.
    """

    name = "autopilot"

    def __init__(self, steer_noise: float = 0.15, throttle_noise: float = 0.15, excursion_rate: float = 0.04,
                 excursion_s: tuple[float, float] = (0.4, 1.5), dt: float = 1.0 / 15.0,
                 params: VehicleParams = VehicleParams()):
        if min(steer_noise, throttle_noise, excursion_rate) < 0 or excursion_rate > 1:
            raise ValueError("autopilot noise levels must be >= 0 and excursion_rate in [0, 1]")
        self.steer_noise, self.throttle_noise = steer_noise, throttle_noise
        self.excursion_rate, self.excursion_s = excursion_rate, tuple(excursion_s)
        self.dt, self.params = dt, params
        self.reset(0)

    def reset(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)
        self.target_speed = None
        self.excursion_left = 0
        self.excursion = np.zeros(2)

    def act(self, obs, info) -> np.ndarray:
        v = float(info["speed"])
        if self.target_speed is None:
            self.target_speed = v
        lookahead = max(6.0, 1.2 * v)
        alpha = math.atan2(EGO_LANE_Y - float(info["y"]), lookahead) - float(info["heading"])
        delta = math.atan(2.0 * self.params.wheelbase * math.sin(alpha) / lookahead)
        steer = -delta / self.params.max_steer          # positive action steers right
        pedal = 0.5 * (self.target_speed - v)
        # Steering noise is a share of the grip-limited wheel angle at this speed: the same action noise
        # that is a gentle wobble at 5 m/s would saturate the tyres at 30 m/s.
        grip_steer = math.atan(self.params.mu * 9.81 * self.params.wheelbase / max(v, 1.0) ** 2)
        steer_sigma = self.steer_noise * min(1.0, grip_steer / self.params.max_steer)
        action = np.array([steer, pedal]) + self.rng.normal(0.0, [steer_sigma, self.throttle_noise])

        if self.excursion_left == 0 and self.rng.random() < self.excursion_rate:
            self.excursion_left = max(1, int(self.rng.uniform(*self.excursion_s) / self.dt))
            if self.rng.random() < 0.5:
                self.excursion = np.array([np.nan, -self.rng.uniform(0.3, 1.0)])       # brake
            else:
                self.excursion = np.array([self.rng.choice([-1.0, 1.0]) * self.rng.uniform(0.3, 1.0), np.nan])
        if self.excursion_left > 0:
            self.excursion_left -= 1
            action = np.where(np.isnan(self.excursion), action, self.excursion)
        return np.clip(action, -1.0, 1.0).astype(np.float32)
