"""A planar 360° LIDAR (Kim et al. 2020: 36 rays, 50 m) cast against the footprints the collisions use (numpy).

Rays start at the ego's centre, the first along its heading, then counter-clockwise in equal steps. Each returns the
distance to the nearest footprint it crosses (other cars' oriented rectangles, pedestrians' circles, the street's
rectangles and posts), or the range when it crosses none. The ego's own footprint is not cast against.
"""

from __future__ import annotations

import math

import numpy as np

from .actors import PEDESTRIAN_RADIUS

N_RAYS, RANGE_M = 36, 50.0


def ray_directions(heading: float, n_rays: int = N_RAYS) -> np.ndarray:
    angles = heading + 2.0 * math.pi * np.arange(n_rays) / n_rays
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def cast(
    origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray, circles: np.ndarray, max_range: float = RANGE_M
) -> np.ndarray:
    """Distances along unit ``dirs`` (R, 2) from ``origin`` to the nearest of ``boxes`` (B, 6: cx, cy, cos, sin,
    half-length, half-width) and ``circles`` (C, 3: cx, cy, r); ``max_range`` where a ray hits nothing in range.
    A ray that starts inside a shape reads 0."""
    best = np.full(len(dirs), float(max_range))
    o = np.asarray(origin, dtype=float)
    if len(boxes):
        b = np.asarray(boxes, dtype=float)
        rel = o[None, :] - b[:, :2]  # (B, 2)
        c, s = b[:, 2], b[:, 3]
        # origin and directions in each box's frame
        ox, oy = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c  # (B,)
        dx = dirs[:, None, 0] * c[None] + dirs[:, None, 1] * s[None]  # (R, B)
        dy = -dirs[:, None, 0] * s[None] + dirs[:, None, 1] * c[None]
        t_near, t_far = _slab(ox[None], dx, b[None, :, 4]), _slab(oy[None], dy, b[None, :, 5])
        enter = np.maximum(t_near[0], t_far[0])
        leave = np.minimum(t_near[1], t_far[1])
        hit = (leave >= np.maximum(enter, 0.0)) & (leave >= 0)
        dist = np.where(hit, np.maximum(enter, 0.0), np.inf)
        best = np.minimum(best, dist.min(axis=1))
    if len(circles):
        cc = np.asarray(circles, dtype=float)
        rel = o[None, :] - cc[:, :2]  # (C, 2)
        proj = dirs @ rel.T  # (R, C): d . (o - c)
        disc = proj**2 - ((rel**2).sum(1) - cc[:, 2] ** 2)[None]
        root = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = -proj - root, -proj + root
        hit = (disc >= 0) & (t1 >= 0)
        dist = np.where(hit, np.maximum(t0, 0.0), np.inf)
        best = np.minimum(best, dist.min(axis=1))
    return best


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit parameters of rays o + t d through the slab |x| <= half (parallel rays: all or nothing)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    parallel = d == 0
    inside = np.abs(o) <= half
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), lo)
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), hi)
    return lo, hi


def scan(env, n_rays: int = N_RAYS, max_range: float = RANGE_M) -> np.ndarray:
    """One scan of ``env`` (an ``UrbanCollisionEnv`` after reset) from its ego, float32 (n_rays,)."""
    ego, act, p = env.ego, env.actors, env.params
    cars = np.flatnonzero(act.car_active)
    boxes = [
        np.column_stack(
            [
                act.car_xy[cars],
                np.cos(act.car_heading[cars]),
                np.sin(act.car_heading[cars]),
                np.full(len(cars), p.length / 2),
                np.full(len(cars), p.width / 2),
            ]
        )
    ]
    rects = env.layout.rects
    if len(rects):
        boxes.append(np.column_stack([rects[:, :2], np.ones(len(rects)), np.zeros(len(rects)), rects[:, 2:4]]))
    peds = np.flatnonzero(act.ped_active)
    circles = [np.column_stack([act.ped_xy[peds], np.full(len(peds), PEDESTRIAN_RADIUS)])]
    if len(env.layout.circles):
        circles.append(env.layout.circles[:, :3])
    dirs = ray_directions(ego.psi, n_rays)
    return cast(np.array([ego.x, ego.y]), dirs, np.concatenate(boxes), np.concatenate(circles), max_range).astype(
        np.float32
    )


class LidarHistory:
    """Kim et al.'s observation: the last ``scans`` LIDAR scans (oldest first, divided by the range) and the
    previous action; before enough scans exist the first is repeated."""

    def __init__(self, scans: int = 4, n_rays: int = N_RAYS, max_range: float = RANGE_M):
        self.scans, self.n_rays, self.max_range = int(scans), int(n_rays), float(max_range)
        self.dim = self.scans * self.n_rays + 2
        self.reset()

    def reset(self, seed=None) -> None:
        self.history: list[np.ndarray] = []
        self.previous_action = np.zeros(2, dtype=np.float32)

    def note_action(self, action) -> None:
        self.previous_action = np.asarray(action, dtype=np.float32).reshape(2)

    def __call__(self, env, obs=None) -> np.ndarray:
        self.history.append(scan(env, self.n_rays, self.max_range) / self.max_range)
        past = self.history[-self.scans :]
        past = [past[0]] * (self.scans - len(past)) + past
        return np.concatenate([*past, self.previous_action]).astype(np.float32)
