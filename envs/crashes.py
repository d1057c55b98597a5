"""What one collision of the ego records: its kind, the impact, each participant's delta-v and injury risk, and
the damaged side of the ego. The env appends one such dict per collision to ``info["collisions"]``."""

from __future__ import annotations

import math

from .injury import damaged_side, occupant_injury, pedestrian_injury, plastic_delta_v
from .scene import CLASS_NAMES


def ego_side(ego, half_length: float, half_width: float, point: tuple[float, float]) -> str:
    """Which side of the ego a contact at world ``point`` damages (front, rear, near = left, far = right)."""
    dx, dy = point[0] - ego.x, point[1] - ego.y
    c, s = math.cos(ego.psi), math.sin(ego.psi)
    return damaged_side(dx * c + dy * s, -dx * s + dy * c, half_length, half_width)


def pedestrian_hit(ego, i: int, t: float, hazard: bool) -> dict:
    risk = pedestrian_injury(ego.v)
    return {
        "kind": "pedestrian",
        "id": int(i),
        "class": "Pedestrians",
        "time": t,
        "hazard": hazard,
        "impact_speed": ego.v,
        "relative_speed": ego.v,
        "delta_v_ego": 0.0,
        "delta_v_other": ego.v,
        "injury": [risk],
        "n_involved": 1,
        "injury_sum": risk,
        "pedestrian_injury": risk,
        "occupant_injury": 0.0,
        "ego_occupant_injury": 0.0,
        "ego_side": "front",
    }


def vehicle_crash(env, i: int, t: float, c: float, s: float, point: tuple[float, float]) -> dict:
    """The ego (heading cosine ``c``, sine ``s``) hitting car ``i`` of ``env``'s actors at ``point``."""
    ego = env.ego
    vx, vy = env.actors.car_vel[i]
    rel = math.hypot(ego.v * c - vx, ego.v * s - vy)
    dv_ego, dv_other = plastic_delta_v(env.ego_mass, env.car_mass, rel)
    p_ego, p_other = occupant_injury(dv_ego), occupant_injury(dv_other)
    n = env.occupants_per_car
    injury = [p_ego] * n + [p_other] * n
    return {
        "kind": "vehicle",
        "id": int(i),
        "class": "Vehicles",
        "time": t,
        "hazard": bool(env.actors.car_hazard[i]),
        "impact_speed": ego.v,
        "relative_speed": rel,
        "delta_v_ego": dv_ego,
        "delta_v_other": dv_other,
        "injury": injury,
        "n_involved": 2 * n,
        "injury_sum": float(sum(injury)),
        "pedestrian_injury": 0.0,
        "occupant_injury": float(sum(injury)),
        "ego_occupant_injury": n * p_ego,
        "ego_side": ego_side(ego, env._hl, env._hw, point),
    }


def static_crash(env, i: int, cls: int, t: float, point: tuple[float, float]) -> dict:
    """The ego hitting static object ``i`` of class ``cls``. A static object is rigid: the ego stops dead, so its
    delta-v is its whole speed."""
    dv = env.ego.v
    n = env.occupants_per_car
    risk = occupant_injury(dv)
    return {
        "kind": "static",
        "id": i,
        "class": CLASS_NAMES[cls],
        "time": t,
        "hazard": False,
        "impact_speed": dv,
        "relative_speed": dv,
        "delta_v_ego": dv,
        "delta_v_other": 0.0,
        "injury": [risk] * n,
        "n_involved": n,
        "injury_sum": n * risk,
        "pedestrian_injury": 0.0,
        "occupant_injury": n * risk,
        "ego_occupant_injury": n * risk,
        "ego_side": ego_side(env.ego, env._hl, env._hw, point),
    }
