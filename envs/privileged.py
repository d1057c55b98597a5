"""The true state as a short vector: what a privileged agent acts on (``obs=privileged``; numpy only).

The paper's DDPG acts on the camera's [z_t, zhat_{t+1}] and loses to straight-line braking. The same learner acting
on this vector instead tells whether the learner or the camera is to blame: it reads, exactly, what the camera has
to make out. Every entry is read from the simulator (``UrbanCollisionEnv``) and scaled to about unit range
(``PRIVILEGED_SCALES``: the vector is the value in its unit divided by the scale). World frame: x along the street
(the ego's direction of travel at the start), y to the left.

====  ================  ====================================================================  =========  ======
 k    name              what                                                                  unit       scale
====  ================  ====================================================================  =========  ======
 0    ped               1 when the hazard pedestrian is there (not yet hit), else 0           -          1
 1    ped_dx            its x minus the ego centre's x                                        m          40
 2    ped_dy            its y minus the ego centre's y                                        m          10
 3    ped_vx            its x velocity minus the ego's                                        m/s        30
 4    ped_vy            its y velocity minus the ego's                                        m/s        10
 5-9  car, car_...      the same for the hazard car (its centre)                              as above
 10   speed             the ego's speed                                                       m/s        30
 11   lane_offset       the ego's y minus its starting lane's centre (+: left)                m          3.5
 12   heading           the ego's heading (+: to the left)                                    rad        1
 13   steer_angle       its road-wheel angle (+: to the left)                                 rad        0.6
 14   yaw_rate          its yaw rate (+: to the left)                                         rad/s      1
 15   left_clear        ahead of the front bumper, the distance to the nearest obstacle in    m          40
                        the lane-wide corridor one lane to the left of the ego; 40 m (1.0)
                        when none is within ``ESCAPE_RANGE_M``
 16   left_closing      that obstacle's x velocity minus the ego's (0 when none)              m/s        30
 17   own_clear         the same in the corridor the ego is in                                m          40
 18   own_closing                                                                             m/s        30
 19   right_clear       the same one lane to the right                                        m          40
 20   right_closing                                                                           m/s        30
====  ================  ====================================================================  =========  ======

Entries 0-9 are ``envs.chooser.hazard_state`` with the ego's velocity taken off the hazards' (zeros when a hazard is
absent). An escape corridor is ``LANE_WIDTH`` wide, centred ``LANE_WIDTH`` to the side of the ego's centre (0 for
its own), and runs along x; an obstacle is anything the ego can hit that overlaps it: a static object of the layout
(rectangle or circle), an active car or an active pedestrian, the hazards among them. An obstacle beside the ego
(between its rear and its front bumper) is at distance 0; one behind the ego's rear does not count.
"""

from __future__ import annotations

import math

import numpy as np

from .actors import PEDESTRIAN_RADIUS
from .chooser import hazard_state
from .scene import LANE_WIDTH

ESCAPE_RANGE_M = 40.0  # how far ahead the escape corridors are searched
CORRIDORS = (("left", LANE_WIDTH), ("own", 0.0), ("right", -LANE_WIDTH))  # lateral offset of each from the ego
PRIVILEGED_STATE = (
    "ped",
    "ped_dx",
    "ped_dy",
    "ped_vx",
    "ped_vy",
    "car",
    "car_dx",
    "car_dy",
    "car_vx",
    "car_vy",
    "speed",
    "lane_offset",
    "heading",
    "steer_angle",
    "yaw_rate",
    *(f"{side}_{what}" for side, _ in CORRIDORS for what in ("clear", "closing")),
)
_HAZARD_SCALES = (1.0, 40.0, 10.0, 30.0, 10.0)
PRIVILEGED_SCALES = np.array(
    [*_HAZARD_SCALES, *_HAZARD_SCALES, 30.0, LANE_WIDTH, 1.0, 0.6, 1.0, *(ESCAPE_RANGE_M, 30.0) * len(CORRIDORS)],
    dtype=np.float64,
)
PRIVILEGED_DIM = len(PRIVILEGED_STATE)


def obstacles(env) -> tuple[np.ndarray, np.ndarray]:
    """Everything the ego can hit now, as axis-aligned boxes ``(n, 4)``: x_lo, x_hi, y_lo, y_hi (m), and each one's
    x velocity ``(n,)`` (m/s; 0 for static objects). Cars are boxed around their heading, the ego's size."""
    a, layout = env.actors, env.layout
    hl, hw = env.params.length / 2, env.params.width / 2
    rects, circles = layout.rects, layout.circles
    parts = [
        np.stack(
            [
                rects[:, 0] - rects[:, 2],
                rects[:, 0] + rects[:, 2],
                rects[:, 1] - rects[:, 3],
                rects[:, 1] + rects[:, 3],
            ],
            1,
        ),
        np.stack(
            [
                circles[:, 0] - circles[:, 2],
                circles[:, 0] + circles[:, 2],
                circles[:, 1] - circles[:, 2],
                circles[:, 1] + circles[:, 2],
            ],
            1,
        ),
    ]
    vx = [np.zeros(len(rects) + len(circles))]
    cars = np.flatnonzero(a.car_active)
    if len(cars):
        c, s = np.abs(np.cos(a.car_heading[cars])), np.abs(np.sin(a.car_heading[cars]))
        ex, ey = c * hl + s * hw, s * hl + c * hw
        x, y = a.car_xy[cars, 0], a.car_xy[cars, 1]
        parts.append(np.stack([x - ex, x + ex, y - ey, y + ey], 1))
        vx.append(a.car_vel[cars, 0])
    peds = np.flatnonzero(a.ped_active)
    if len(peds):
        x, y, r = a.ped_xy[peds, 0], a.ped_xy[peds, 1], PEDESTRIAN_RADIUS
        parts.append(np.stack([x - r, x + r, y - r, y + r], 1))
        vx.append(a.ped_vel[peds, 0])
    return np.concatenate(parts).reshape(-1, 4), np.concatenate(vx)


def corridor_clearance(env, offset: float, boxes=None, range_m: float = ESCAPE_RANGE_M) -> tuple[float, float]:
    """(distance ahead of the front bumper to the nearest obstacle in the lane-wide corridor centred ``offset`` m to
    the left of the ego, capped at ``range_m``; that obstacle's x velocity minus the ego's, 0 when none) in m and
    m/s. ``boxes``: ``obstacles(env)``, when the caller has them."""
    e = env.ego
    boxes, vx = obstacles(env) if boxes is None else boxes
    hl = env.params.length / 2
    front, rear = e.x + hl, e.x - hl
    centre = e.y + offset
    inside = (
        (boxes[:, 2] < centre + LANE_WIDTH / 2)
        & (boxes[:, 3] > centre - LANE_WIDTH / 2)
        & (boxes[:, 1] > rear)
        & (boxes[:, 0] < front + range_m)
    )
    if not inside.any():
        return float(range_m), 0.0
    gap = np.maximum(boxes[inside, 0] - front, 0.0)
    k = int(np.argmin(gap))
    return float(gap[k]), float(vx[inside][k] - e.v * math.cos(e.psi))


def privileged_state(env) -> np.ndarray:
    """The privileged observation of ``env`` now, scaled (``PRIVILEGED_STATE``, the module docstring): float32
    ``(PRIVILEGED_DIM,)``. ``env``: a reset ``UrbanCollisionEnv``."""
    e = env.ego
    raw = np.zeros(PRIVILEGED_DIM, np.float64)
    raw[:10] = hazard_state(env)
    ego_v = (e.v * math.cos(e.psi), e.v * math.sin(e.psi))
    for k in (0, 5):  # relative velocities of the hazards that are there
        if raw[k]:
            raw[k + 3] -= ego_v[0]
            raw[k + 4] -= ego_v[1]
    raw[10:15] = (e.v, e.y - env.lane_y, e.psi, e.delta, e.r)
    boxes = obstacles(env)
    for i, (_, offset) in enumerate(CORRIDORS):
        raw[15 + 2 * i : 17 + 2 * i] = corridor_clearance(env, offset, boxes)
    return (raw / PRIVILEGED_SCALES).astype(np.float32)
