"""Other traffic participants: cars and pedestrians moving kinematically at constant velocity.

As in the paper, nobody reacts to the ego, and participants pass through one another (only contacts with
the ego are modelled). Because nobody reacts, traffic in the ego's own lane is placed ahead of it and
never slower than it, so braking can never cause a rear-end crash with a follower that does not exist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .scenario import ScenarioSpec
from .scene import EGO_LANE_Y, ONCOMING_LANE_Y, SCENE_X, SIDEWALK_OUTER

CAR_POOL = 12  # 10 others + the hazard car + one spare
PEDESTRIAN_POOL = 12
PEDESTRIAN_RADIUS = 0.3
PEDESTRIAN_HALF_SIZE = (0.25, 0.3, 0.875)  # box used for rendering
CROSSING_ANGLE_DEG = 30.0  # hazard pedestrians cross within +-30 deg of perpendicular


@dataclass
class Actors:
    car_xy: np.ndarray  # (CAR_POOL, 2) centres
    car_vel: np.ndarray  # (CAR_POOL, 2)
    car_heading: np.ndarray  # (CAR_POOL,)
    car_active: np.ndarray  # (CAR_POOL,) bool
    car_hazard: np.ndarray  # (CAR_POOL,) bool
    ped_xy: np.ndarray
    ped_vel: np.ndarray
    ped_active: np.ndarray  # False once hit or unused
    ped_hazard: np.ndarray
    ped_stop_y: np.ndarray  # a crossing pedestrian stops once it walks past this y (nan = never)
    collision_point: tuple[float, float] | None  # where the ego's front bumper is at TTC

    @classmethod
    def empty(cls, collision_point: tuple[float, float] | None = None) -> Actors:
        """Every pool slot unused and at rest: a family's ``build`` activates the ones it places."""
        cars, peds = np.zeros((CAR_POOL, 2)), np.zeros((PEDESTRIAN_POOL, 2))
        return cls(
            car_xy=cars,
            car_vel=cars.copy(),
            car_heading=np.zeros(CAR_POOL),
            car_active=np.zeros(CAR_POOL, dtype=bool),
            car_hazard=np.zeros(CAR_POOL, dtype=bool),
            ped_xy=peds,
            ped_vel=peds.copy(),
            ped_active=np.zeros(PEDESTRIAN_POOL, dtype=bool),
            ped_hazard=np.zeros(PEDESTRIAN_POOL, dtype=bool),
            ped_stop_y=np.full(PEDESTRIAN_POOL, np.nan),
            collision_point=collision_point,
        )

    def advance(self, dt: float) -> None:
        self.car_xy += self.car_vel * dt
        self.ped_xy += self.ped_vel * dt
        with np.errstate(invalid="ignore"):
            arrived = (self.ped_xy[:, 1] - self.ped_stop_y) * np.sign(self.ped_vel[:, 1]) > 0.0
        if arrived.any():
            self.ped_vel[arrived] = 0.0
            self.ped_stop_y[arrived] = np.nan


def build_actors(
    spec: ScenarioSpec, rng: np.random.Generator, ego_x0: float, ego_front: float, car_length: float, car_width: float
) -> tuple[Actors, float]:
    """Place hazards and traffic for ``spec``; returns the actors and the junction position."""
    bumper_at_ttc = ego_x0 + ego_front + spec.ego_speed * spec.ttc
    actors = Actors.empty((bumper_at_ttc, EGO_LANE_Y) if spec.hazard != "none" else None)
    car_xy, car_vel, car_heading, car_active = actors.car_xy, actors.car_vel, actors.car_heading, actors.car_active
    ped_xy, ped_vel, ped_active, ped_stop_y = actors.ped_xy, actors.ped_vel, actors.ped_active, actors.ped_stop_y
    junction_x = bumper_at_ttc + car_width / 2 if spec.car_hazard else float(rng.uniform(30.0, 150.0))

    n_car = n_ped = 0
    if spec.car_hazard:
        # Out of the side street: the car's near side reaches the ego's path when the bumper does.
        side = 1.0 if rng.random() < 0.5 else -1.0  # +1: from the left (+y), driving towards -y
        v = spec.hazard_car_speed
        car_xy[0] = (junction_x, EGO_LANE_Y + side * v * spec.ttc)
        car_vel[0] = (0.0, -side * v)
        car_heading[0] = -side * math.pi / 2
        car_active[0] = actors.car_hazard[0] = True
        n_car = 1
    if spec.pedestrian_hazard:
        v = spec.pedestrian_speed
        reach = v * spec.ttc
        offset = float(rng.uniform(-0.5, 0.5))  # where across the bumper they meet
        angle = math.radians(float(rng.uniform(-CROSSING_ANGLE_DEG, CROSSING_ANGLE_DEG)))
        meet = (bumper_at_ttc + PEDESTRIAN_RADIUS, EGO_LANE_Y + offset)
        # Start on a sidewalk: from the right only if the walk fits within the near sidewalk.
        right_ok = meet[1] - reach * math.cos(angle) >= -(SIDEWALK_OUTER - 0.2)
        side = -1.0 if (right_ok and rng.random() < 0.5) else 1.0
        direction = np.array([math.sin(angle), -side * math.cos(angle)])
        ped_xy[0] = np.array(meet) - direction * reach
        ped_vel[0] = direction * v
        ped_stop_y[0] = side * -(SIDEWALK_OUTER - 1.0)  # on the far sidewalk
        ped_active[0] = actors.ped_hazard[0] = True
        n_ped = 1

    # Oncoming traffic anywhere ahead or beside; same-direction traffic well beyond the collision point.
    same_lane_speed = spec.ego_speed * float(rng.uniform(1.0, 1.2))
    next_same = bumper_at_ttc + 15.0 + float(rng.uniform(0.0, 20.0))
    next_oncoming = ego_x0 - 20.0 + float(rng.uniform(0.0, 15.0))
    for _ in range(spec.n_cars):
        if rng.random() < 0.4:
            car_xy[n_car] = (next_same, EGO_LANE_Y)
            car_vel[n_car] = (same_lane_speed, 0.0)
            car_heading[n_car] = 0.0
            next_same += car_length + float(rng.uniform(8.0, 40.0))
        else:
            car_xy[n_car] = (next_oncoming, ONCOMING_LANE_Y)
            car_vel[n_car] = (-float(rng.uniform(6.0, 14.0)), 0.0)
            car_heading[n_car] = math.pi
            next_oncoming += car_length + float(rng.uniform(8.0, 40.0))
        car_active[n_car] = True
        n_car += 1

    for _ in range(spec.n_pedestrians):
        side = 1.0 if rng.random() < 0.5 else -1.0
        ped_xy[n_ped] = (
            float(rng.uniform(ego_x0 - 10.0, min(SCENE_X[1], ego_x0 + 150.0))),
            side * float(rng.uniform(4.3, 6.0)),
        )
        ped_vel[n_ped] = ((1.0 if rng.random() < 0.5 else -1.0) * float(rng.uniform(0.8, 1.8)), 0.0)
        ped_active[n_ped] = True
        n_ped += 1

    return actors, junction_x
