"""Ego vehicle: a kinematic single-track (bicycle) model with actuator and tyre limits.

State: position (x, y) of the centre, heading psi, speed v, road-wheel angle delta, yaw rate r.

Why these limits, and where their values come from:

* ``max_steer`` 0.6 rad (34 deg) road-wheel angle, typical of passenger cars
  (CommonRoad's vehicle parameter sets list 0.91 rad for the Ford Escort model, which includes lock-to-lock
  parking manoeuvres; at speed the friction limit below binds long before either).
* ``max_steer_rate`` 1.0 rad/s road-wheel: an emergency hand-wheel rate of about 900 deg/s through a 15:1
  steering ratio. CommonRoad uses 0.4 rad/s for normal driving; emergency steering is faster.
* ``yaw_lag_s`` 0.15 s: yaw rate follows the kinematic target through a first-order lag. A kinematic
  model turns instantly, which would let a car at 30 m/s move sideways by ~1 m in 0.5 s; real cars need
  roughly 0.1-0.3 s to build up yaw rate (tyre relaxation and yaw inertia), which is what makes late
  swerves only partly effective.
* friction circle: lateral (v * r) and longitudinal acceleration together stay within mu * g. Lateral grip
  is served first (as an ABS car keeps steering while braking) and braking gets what is left, so full
  braking with the wheel straight (9.8 m/s^2) stays just inside mu * g (9.81 m/s^2 at mu = 1).
* ``max_accel`` 3.0 m/s^2 at full throttle (a mid-size petrol car, 0-100 km/h in ~9 s).
* brake request: action -1..0 maps linearly to 9.8..0 m/s^2 (the paper's action space, section III-C).

Length 4.5 m, width 1.8 m, wheelbase 2.7 m: a mid-size saloon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

G = 9.81
MAX_BRAKE_DECEL = 9.8  # m/s^2 at action[1] == -1, as the paper's action space defines it


@dataclass(frozen=True)
class VehicleParams:
    length: float = 4.5
    width: float = 1.8
    height: float = 1.5
    wheelbase: float = 2.7
    max_steer: float = 0.6
    max_steer_rate: float = 1.0
    yaw_lag_s: float = 0.15
    max_accel: float = 3.0
    max_speed: float = 40.0
    mu: float = 1.0
    mass: float = 1500.0


@dataclass
class VehicleState:
    x: float
    y: float
    psi: float
    v: float
    delta: float = 0.0
    r: float = 0.0

    def copy(self) -> VehicleState:
        return VehicleState(self.x, self.y, self.psi, self.v, self.delta, self.r)


def requested_accel(throttle_brake: float, p: VehicleParams) -> float:
    """Longitudinal acceleration asked for by the second action channel."""
    u = min(1.0, max(-1.0, throttle_brake))
    return u * MAX_BRAKE_DECEL if u < 0.0 else u * p.max_accel


def integrate(s: VehicleState, steer: float, throttle_brake: float, dt: float, p: VehicleParams) -> None:
    """Advance ``s`` in place by ``dt`` (semi-implicit Euler; callers sub-step at ~1/120 s)."""
    grip = p.mu * G
    target_delta = min(1.0, max(-1.0, steer)) * p.max_steer
    # Positive steer is a right turn (the paper maps -1..1 to max left..max right); heading is counter-
    # clockwise, so a right turn lowers psi.
    target_delta = -target_delta
    max_step = p.max_steer_rate * dt
    s.delta += min(max_step, max(-max_step, target_delta - s.delta))

    v = s.v
    r_target = v * math.tan(s.delta) / p.wheelbase
    if v > 0.1:
        r_cap = grip / v
        r_target = min(r_cap, max(-r_cap, r_target))
    s.r += (r_target - s.r) * min(1.0, dt / p.yaw_lag_s)

    a_lat = v * s.r
    a_long_budget = math.sqrt(max(0.0, grip * grip - a_lat * a_lat))
    a_long = requested_accel(throttle_brake, p)
    a_long = min(a_long_budget, max(-a_long_budget, a_long))

    new_v = v + a_long * dt
    if new_v <= 0.0:
        # Brakes cannot push the car backwards: it stops within the step.
        new_v = 0.0
        s.r = 0.0
    new_v = min(new_v, p.max_speed)
    v_mid = 0.5 * (v + new_v)
    s.psi += s.r * dt
    s.x += v_mid * math.cos(s.psi) * dt
    s.y += v_mid * math.sin(s.psi) * dt
    s.v = new_v
