"""The pybullet side of the street: every body created once per env, then moved per episode and per frame.

Every episode re-randomises the layout (``envs.scene.sample_layout``) by *moving* pooled bodies, never creating
new ones, so resets stay cheap and memory stays flat. Bodies a layout does not use are parked below the ground and
hidden (alpha 0, which TinyRenderer skips). The flat ground's bodies stay, hidden, as the reference the camera's
per-pixel ground reproduces, and for the bird's-eye view (``envs/camera.py`` explains why and what it costs).
Only the env's camera mode builds this module's pool; the camera-off mode needs no pybullet at all.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys

import numpy as np

from .scene import (
    BUILDING_HEIGHT_COUNTS,
    BUILDING_HEIGHTS,
    BUILDINGS,
    FIXED_BOXES,
    GROUND_POOLS,
    NUM_CLASSES,
    PALETTE,
    PARK_Z,
    PEDESTRIANS,
    SIDEWALK_HEIGHT,
    TEMPLATES,
    VEHICLES,
    StaticLayout,
)


@contextlib.contextmanager
def c_output_silenced():
    """Swallow what C code writes on the process's stdout and stderr inside the block: pybullet writes its build
    time when imported, and every worker of a run would repeat it. Python exceptions are unaffected: they are
    raised, and printed, after the block."""
    import ctypes

    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            os.dup2(devnull.fileno(), 2)
            try:
                yield
            finally:
                ctypes.CDLL(None).fflush(None)
    finally:
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)


class BodyPool:
    """The pybullet side of the scene: every body created once, then moved per episode and per frame.

    What TinyRenderer draws is controlled by colour alpha: pybullet skips a body with alpha 0 entirely (a
    parked body still costs its vertex work, about 4 us). Bodies the layout does not use, inactive actors and
    the flat ground (drawn by the camera itself, see ``camera.FlatGround``) are hidden; ``show`` hides in-use bodies
    the camera cannot see, one ``changeVisualShape`` per body whose state changes.
    """

    def __init__(self, client: int, n_cars: int, n_pedestrians: int, vehicle_size: tuple, pedestrian_size: tuple):
        import pybullet as p

        self._p = p
        self.client = client
        self.uid_class: dict[int, int] = {}
        self.pools: dict[str, list[int]] = {}
        rgba: list[list[float]] = []
        radius: list[float] = []
        height: list[float] = []
        halves: list[list[float]] = []

        def make(cls: int, shape: str, size: tuple, pos=(0.0, 0.0, PARK_Z)) -> int:
            colour = list(PALETTE[cls] / 255.0) + [1.0]
            half = list(size) if shape == "box" else [size[0], size[0], size[1] / 2]
            vs = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=colour, physicsClientId=client)
            uid = p.createMultiBody(baseMass=0, baseVisualShapeIndex=vs, basePosition=list(pos), physicsClientId=client)
            if uid != len(rgba):
                raise RuntimeError("BodyPool needs a fresh pybullet client (body ids 0, 1, 2, ...)")
            self.uid_class[uid] = cls
            rgba.append(colour)
            radius.append(float(np.hypot(half[0], half[1])))
            height.append(float(half[2]))
            halves.append(half)
            return uid

        fixed = [make(cls, "box", half, centre) for cls, half, centre in FIXED_BOXES]
        # Buildings: per template, (full height, uids) from the lowest to the tallest.
        self.buildings: dict[str, list[tuple[float, list[int]]]] = {}
        for name, tmpl in TEMPLATES.items():
            if tmpl.cls == BUILDINGS:
                hx, hy, _ = tmpl.size
                self.buildings[name] = [
                    (h, [make(tmpl.cls, "box", (hx, hy, h / 2)) for _ in range(k or tmpl.count)])
                    for h, k in zip(BUILDING_HEIGHTS, BUILDING_HEIGHT_COUNTS)
                ]
                self.pools[name] = [u for _, uids in self.buildings[name] for u in uids]
            else:
                self.pools[name] = [make(tmpl.cls, tmpl.shape, tmpl.size) for _ in range(tmpl.count)]
        half_car = (vehicle_size[0] / 2, vehicle_size[1] / 2, vehicle_size[2] / 2)
        self.cars = [make(VEHICLES, "box", half_car) for _ in range(n_cars)]
        self.pedestrians = [make(PEDESTRIANS, "box", pedestrian_size) for _ in range(n_pedestrians)]
        # The ego's own body exists only for the bird's-eye view; the forward camera never sees it.
        self.ego = make(VEHICLES, "box", half_car)
        n = len(rgba)
        self.lut = np.zeros(n + 1, dtype=np.uint8)  # index uid+1; -1 (sky) -> None
        for uid, cls in self.uid_class.items():
            self.lut[uid + 1] = cls
        self._car_half_height = half_car[2]
        self._ped_half_height = pedestrian_size[2]

        self._rgba = rgba
        self.ground_uids = np.array(fixed + [u for name in GROUND_POOLS for u in self.pools[name]])
        # One body per class stands for the flat ground's pixels in the uid frame (road, sidewalk, edge line).
        self.ground_uid = np.full(NUM_CLASSES, -1, dtype=np.int32)
        for uid in fixed:
            if self.ground_uid[self.uid_class[uid]] < 0:
                self.ground_uid[self.uid_class[uid]] = uid
        # Per body: footprint centre and bounding radius, z range (for culling), in use, drawn (alpha 1).
        self.centre = np.zeros((n, 2))
        self.radius = np.array(radius)
        self.z = np.full((n, 2), PARK_Z)
        self.in_use = np.zeros(n, dtype=bool)
        self.shown = np.ones(n, dtype=bool)  # as created
        for uid in fixed:  # fixed ground: in place, and in use, for ever
            _, _, centre_z = FIXED_BOXES[uid][2]
            self.centre[uid] = FIXED_BOXES[uid][2][:2]
            self.z[uid] = (centre_z - height[uid], centre_z + height[uid])
            self.in_use[uid] = True
        self._half_height = np.array(height)
        self._index_road_users(halves)
        self._cullable = np.ones(n, dtype=bool)
        self._cullable[self.ground_uids] = False
        self._cullable[self.ego] = False
        self._cars = np.array(self.cars)
        self._peds = np.array(self.pedestrians)
        self.z[self._cars] = (0.0, 2.0 * self._car_half_height)  # where actors stand when active
        self.z[self._peds] = (SIDEWALK_HEIGHT, SIDEWALK_HEIGHT + 2.0 * self._ped_half_height)
        self.show(np.zeros(n, dtype=bool))

    def _index_road_users(self, halves: list) -> None:
        """Per body its box's half extents and heading (radians; only cars turn), and which bodies are road users
        (pedestrians and vehicles, the ego's own body left out): what the camera's cover of road users projects."""
        self.half_extents = np.array(halves, dtype=np.float64)
        self.heading = np.zeros(len(halves))
        road = np.isin(self.lut[1:], (PEDESTRIANS, VEHICLES))
        road[self.ego] = False
        self.road_users = np.flatnonzero(road)

    # ------------------------------------------------------------------ placing
    def _move(self, uid: int, pos) -> None:
        self._p.resetBasePositionAndOrientation(uid, pos, (0.0, 0.0, 0.0, 1.0), physicsClientId=self.client)
        self.centre[uid] = pos[:2]
        h = self._half_height[uid]
        self.z[uid] = (pos[2] - h, pos[2] + h)

    def _building_spots(self, name: str, spots: list) -> dict[int, tuple]:
        """uid -> position for the layout's buildings of one template: the lowest free box that is tall enough."""
        top = TEMPLATES[name].size[2]  # the layout places the template's box: centre z = height - top
        free = [list(uids) for _, uids in self.buildings[name]]
        out = {}
        for cx, cy, cz in spots:
            height = cz + top
            k = next(i for i, (h, _) in enumerate(self.buildings[name]) if h >= height - 1e-9 and free[i])
            h = self.buildings[name][k][0]
            out[free[k].pop(0)] = (cx, cy, height - h / 2)
        return out

    def apply_layout(self, layout: StaticLayout) -> None:
        for name, uids in self.pools.items():
            spots = layout.placements.get(name, [])
            if name in self.buildings:
                placed = self._building_spots(name, spots)
                for uid in uids:
                    if uid in placed or self.in_use[uid]:
                        self._move(uid, placed.get(uid, (0.0, 0.0, PARK_Z)))
                    self.in_use[uid] = uid in placed
                continue
            for i, uid in enumerate(uids):
                used = i < len(spots)
                # An unused body only moves if it was in use: it is hidden, and parked since its last use.
                if used or self.in_use[uid]:
                    self._move(uid, spots[i] if used else (0.0, 0.0, PARK_Z))
                self.in_use[uid] = used

    def place_actors(self, car_xy, car_heading, car_active, ped_xy, ped_active) -> None:
        """Move the active cars and pedestrians; park the ones that just became inactive (hidden anyway)."""
        reset, c = self._p.resetBasePositionAndOrientation, self.client
        zc = self._car_half_height
        zp = self._ped_half_height + SIDEWALK_HEIGHT
        was = self.in_use.tolist()
        for uid, on, (x, y), h in zip(self.cars, car_active.tolist(), car_xy.tolist(), car_heading.tolist()):
            if on:
                reset(uid, (x, y, zc), (0.0, 0.0, math.sin(0.5 * h), math.cos(0.5 * h)), physicsClientId=c)
            elif was[uid]:
                reset(uid, (0.0, 0.0, PARK_Z), (0.0, 0.0, 0.0, 1.0), physicsClientId=c)
        for uid, on, (x, y) in zip(self.pedestrians, ped_active.tolist(), ped_xy.tolist()):
            if on:
                reset(uid, (x, y, zp), (0.0, 0.0, 0.0, 1.0), physicsClientId=c)
            elif was[uid]:
                reset(uid, (0.0, 0.0, PARK_Z), (0.0, 0.0, 0.0, 1.0), physicsClientId=c)
        self.in_use[self._cars] = car_active
        self.in_use[self._peds] = ped_active
        self.centre[self._cars] = car_xy
        self.centre[self._peds] = ped_xy
        self.heading[self._cars] = car_heading

    def place_ego(self, x: float, y: float, heading: float, visible: bool) -> None:
        h = 0.5 * heading
        pos = (x, y, self._car_half_height) if visible else (0.0, 0.0, PARK_Z)
        self._p.resetBasePositionAndOrientation(
            self.ego, pos, (0.0, 0.0, math.sin(h), math.cos(h)), physicsClientId=self.client
        )
        self.in_use[self.ego] = visible

    # ------------------------------------------------------------------ what TinyRenderer draws
    def show(self, want: np.ndarray) -> None:
        """Draw exactly the bodies in the boolean mask ``want`` (indexed by uid)."""
        change = np.flatnonzero(want != self.shown)
        if change.size:
            p, c = self._p, self.client
            for uid in change.tolist():
                colour = self._rgba[uid] if want[uid] else self._rgba[uid][:3] + [0.0]
                p.changeVisualShape(uid, -1, rgbaColor=colour, physicsClientId=c)
            self.shown = want.copy()

    def cullable_in_use(self) -> np.ndarray:
        """Bodies in use that are drawn by TinyRenderer (not the flat ground, not the ego)."""
        return self.in_use & self._cullable

    def show_everything(self, ground: bool = True) -> None:
        """Draw every body in use, and the flat ground's bodies (bird's-eye view, reference renders)."""
        want = self.in_use.copy()
        if not ground:
            want[self.ground_uids] = False
        self.show(want)
