"""The static urban street: class ids, road geometry, per-episode layout, and the pybullet body pool.

World frame: x along the main street (the ego drives towards +x in the right-hand lane), y to the left,
z up, metres. The road is two 3.5 m lanes (ego lane centred at y=-1.75, oncoming at +1.75), with
sidewalks to |y|=6.5 and buildings set back behind them. One junction with a side street crosses the
street; a crossing hazard car comes out of it.

The world is built once per env as a pool of pybullet bodies. Every episode re-randomises the layout from
the scenario seed (building setbacks, heights and spacing, poles, signs, trees, fences, walls, bins, the
junction position) by *moving* pooled bodies, never creating new ones, so resets stay cheap and memory
stays flat. Bodies a layout does not use are parked below the ground and hidden (alpha 0, which TinyRenderer
skips). The flat ground is drawn by the camera per pixel from ``FlatGround``; its bodies stay, hidden, as the
reference and for the bird's-eye view (``envs/camera.py`` explains why and what it costs).

Collision footprints are kept here as plain arrays (axis-aligned rectangles and circles in the x-y plane):
the collision model (``envs.geometry``) is exact 2D geometry in numpy, so the camera-off mode needs no
pybullet at all and camera on/off give identical outcomes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

CLASS_NAMES = (
    "None", "Buildings", "Fences", "Other", "Pedestrians", "Poles", "RoadLines",
    "Roads", "Sidewalks", "Vegetation", "Vehicles", "Walls", "TrafficSigns",
)
NUM_CLASSES = len(CLASS_NAMES)
(NONE, BUILDINGS, FENCES, OTHER, PEDESTRIANS, POLES, ROADLINES,
 ROADS, SIDEWALKS, VEGETATION, VEHICLES, WALLS, TRAFFICSIGNS) = range(NUM_CLASSES)

# CARLA's Cityscapes-style palette, so frames look like the paper's Fig. 4.
PALETTE = np.array([
    (0, 0, 0), (70, 70, 70), (190, 153, 153), (250, 170, 160), (220, 20, 60), (153, 153, 153),
    (157, 234, 50), (128, 64, 128), (244, 35, 232), (107, 142, 35), (0, 0, 142), (102, 102, 156),
    (220, 220, 0),
], dtype=np.uint8)

LANE_WIDTH = 3.5
EGO_LANE_Y = -1.75
ONCOMING_LANE_Y = 1.75
ROAD_HALF_WIDTH = 3.5
SIDEWALK_OUTER = 6.5
SIDEWALK_HEIGHT = 0.15
SCENE_X = (-40.0, 330.0)
JUNCTION_HALF_WIDTH = 6.0   # half the side street's width; buildings keep clear of it
PARK_Z = -60.0              # where unused pool bodies wait, far below the ground


@dataclass(frozen=True)
class Template:
    """One kind of pooled body: a box (half extents) or a post (radius, height).

    Posts collide as circles but render as square boxes: pybullet tessellates cylinders into hundreds of
    triangles, which made TinyRenderer several times slower for no visible gain at 64x64.
    """
    cls: int
    shape: str
    size: tuple
    count: int


# Pool sizes bound what a layout can use; the layout sampler never asks for more.
TEMPLATES: dict[str, Template] = {
    "building_long": Template(BUILDINGS, "box", (8.0, 5.0, 12.0), 16),
    "building_short": Template(BUILDINGS, "box", (4.5, 5.0, 12.0), 16),
    "pole": Template(POLES, "post", (0.12, 6.0), 28),
    "sign_post": Template(POLES, "post", (0.06, 2.2), 10),
    "sign_plate": Template(TRAFFICSIGNS, "box", (0.04, 0.35, 0.35), 10),
    "trunk": Template(VEGETATION, "post", (0.2, 3.0), 16),
    "crown": Template(VEGETATION, "box", (1.4, 1.4, 1.2), 16),
    "hedge": Template(VEGETATION, "box", (2.0, 0.5, 0.5), 10),
    "fence": Template(FENCES, "box", (4.0, 0.05, 0.6), 10),
    "wall": Template(WALLS, "box", (5.0, 0.15, 1.0), 8),
    "bin": Template(OTHER, "box", (0.3, 0.3, 0.5), 8),
    "dash": Template(ROADLINES, "box", (1.5, 0.08, 0.01), 64),
    "side_street": Template(ROADS, "box", (JUNCTION_HALF_WIDTH, 20.0, 0.01), 2),
}

# The flat ground: fixed, never-moving boxes (class, half extents, centre). Their tops are at ROAD_TOP_Z (road),
# ROAD_TOP_Z + 0.002 (edge lines) and SIDEWALK_TOP_Z (sidewalks, a 0.15 m kerb above the road).
_X_MID = 0.5 * (SCENE_X[0] + SCENE_X[1])
_X_HALF = 0.5 * (SCENE_X[1] - SCENE_X[0]) + 40.0
GROUND_X = (_X_MID - _X_HALF, _X_MID + _X_HALF)   # the ground's extent along the street
SIDEWALK_WIDTH = 40.0                             # sidewalk boxes reach |y| = 3.5 + 40 (the land behind them)
ROAD_TOP_Z = 0.01
SIDEWALK_TOP_Z = SIDEWALK_HEIGHT - 0.01
LINE_HALF_WIDTH = 0.08
EDGE_LINE_Y = ROAD_HALF_WIDTH - 0.2
FIXED_BOXES = (
    (ROADS, (_X_HALF, ROAD_HALF_WIDTH, ROAD_TOP_Z), (_X_MID, 0.0, 0.0)),              # carriageway
    (SIDEWALKS, (_X_HALF, SIDEWALK_WIDTH / 2, SIDEWALK_HEIGHT / 2),
     (_X_MID, ROAD_HALF_WIDTH + SIDEWALK_WIDTH / 2, SIDEWALK_TOP_Z - SIDEWALK_HEIGHT / 2)),
    (SIDEWALKS, (_X_HALF, SIDEWALK_WIDTH / 2, SIDEWALK_HEIGHT / 2),
     (_X_MID, -ROAD_HALF_WIDTH - SIDEWALK_WIDTH / 2, SIDEWALK_TOP_Z - SIDEWALK_HEIGHT / 2)),
    (ROADLINES, (_X_HALF, LINE_HALF_WIDTH, 0.012), (_X_MID, EDGE_LINE_Y, 0.0)),  # solid edge lines
    (ROADLINES, (_X_HALF, LINE_HALF_WIDTH, 0.012), (_X_MID, -EDGE_LINE_Y, 0.0)),
)
# Pools whose bodies lie flat on the ground; the camera draws them analytically (``FlatGround``).
GROUND_POOLS = ("dash", "side_street")
# A building's visible height is drawn from 6..24 m. Rather than sinking one 24 m box up to 18 m into the ground
# (TinyRenderer still rasterises the buried part: about a quarter of the buildings' cost), the pool holds boxes of
# these full heights (m) and uses the lowest free one that reaches the layout's height, buried by < 3 m.
# Counts per building template; the tallest holds the template's whole count, so a layout never runs out.
BUILDING_HEIGHTS = (9.0, 12.0, 15.0, 18.0, 21.0, 24.0)
BUILDING_HEIGHT_COUNTS = (6, 6, 6, 6, 6, None)   # None: the template's count


@dataclass
class StaticLayout:
    """Where every pooled body goes this episode, and the obstacles the ego can crash into."""
    junction_x: float
    placements: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)
    rects: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))    # cx, cy, hx, hy, class
    circles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # cx, cy, r, class


def sample_layout(rng: np.random.Generator, junction_x: float) -> StaticLayout:
    """Draw a street layout around a junction at ``junction_x``. Pure numpy: no pybullet needed."""
    placed: dict[str, list] = {name: [] for name in TEMPLATES}
    rects: list[tuple] = []
    circles: list[tuple] = []

    def near_junction(x: float, half: float, margin: float = 1.0) -> bool:
        return abs(x - junction_x) < JUNCTION_HALF_WIDTH + half + margin

    for side in (+1.0, -1.0):
        # Buildings: a row of blocks with random lengths, gaps, setbacks and visible heights.
        x = SCENE_X[0]
        used = {"building_long": 0, "building_short": 0}
        while x < SCENE_X[1]:
            name = "building_long" if rng.random() < 0.5 else "building_short"
            if used[name] >= TEMPLATES[name].count // 2:
                name = "building_short" if name == "building_long" else "building_long"
                if used[name] >= TEMPLATES[name].count // 2:
                    break
            hx, hy, hz = TEMPLATES[name].size
            gap = rng.uniform(0.0, 6.0)
            cx = x + gap + hx
            if near_junction(cx, hx):
                x = junction_x + JUNCTION_HALF_WIDTH + 0.5
                continue
            setback = rng.uniform(0.0, 4.0)
            height = rng.uniform(6.0, 24.0)
            cy = side * (SIDEWALK_OUTER + setback + hy)
            placed[name].append((cx, cy, height - hz))   # sunk so that ``height`` shows above ground
            rects.append((cx, cy, hx, hy, BUILDINGS))
            used[name] += 1
            x = cx + hx
        # Street furniture along the kerb and the back of the sidewalk.
        for name, y_abs, spacing in (("pole", 3.85, (18.0, 30.0)), ("trunk", 4.6, (15.0, 40.0))):
            x = SCENE_X[0] + rng.uniform(0.0, spacing[0])
            while x < SCENE_X[1] and len(placed[name]) < TEMPLATES[name].count:
                if not near_junction(x, 0.5):
                    r, h = TEMPLATES[name].size
                    cy = side * y_abs
                    placed[name].append((x, cy, h / 2))
                    circles.append((x, cy, r, TEMPLATES[name].cls))
                    if name == "trunk":
                        placed["crown"].append((x, cy, h + 0.8))
                x += rng.uniform(*spacing)
        for name, y_abs in (("sign_post", 3.9), ("bin", 5.8), ("hedge", 6.0), ("fence", 6.35), ("wall", 6.6)):
            tmpl = TEMPLATES[name]
            for _ in range(tmpl.count // 2):
                x = rng.uniform(SCENE_X[0], SCENE_X[1] - 20.0)
                half = tmpl.size[0]
                if near_junction(x, half):
                    continue
                cy = side * y_abs
                if tmpl.shape == "post":
                    r, h = tmpl.size
                    placed[name].append((x, cy, h / 2))
                    circles.append((x, cy, r, tmpl.cls))
                    placed["sign_plate"].append((x, cy, h + 0.2))
                else:
                    hx, hy, hz = tmpl.size
                    placed[name].append((x, cy, hz + SIDEWALK_HEIGHT))
                    rects.append((x, cy, hx, hy, tmpl.cls))

    # Centre-line dashes (6 m period) over the stretch the camera can see; none across the junction.
    x0 = rng.uniform(0.0, 6.0) - 20.0
    for k in range(TEMPLATES["dash"].count):
        x = x0 + 6.0 * k
        if not near_junction(x, 1.5, margin=0.0):
            placed["dash"].append((x, 0.0, 0.0))
    for side in (+1.0, -1.0):
        placed["side_street"].append((junction_x, side * (ROAD_HALF_WIDTH + 20.0), SIDEWALK_HEIGHT + 0.002))

    return StaticLayout(
        junction_x=junction_x,
        placements=placed,
        rects=np.array(rects, dtype=np.float64).reshape(-1, 5),
        circles=np.array(circles, dtype=np.float64).reshape(-1, 4),
    )


class FlatGround:
    """The flat ground of one layout (road, sidewalks with their kerb, edge lines, centre-line dashes, the side
    street) as plain geometry, so the camera can draw it per pixel instead of rasterising its huge triangles.

    The pooled ground bodies still exist (hidden) and are the reference this reproduces: ``classify`` answers,
    for downward rays, what those boxes show. A ray meets the sidewalk level (``UPPER_Z``, where sidewalk tops
    and the side street are) first, then the road level (``LOWER_Z``). A ray that passes the sidewalk level over
    the road but is over a sidewalk at the road level has hit the kerb's face: Sidewalks, at the depth where it
    crosses the kerb line. The side street's top (2 cm above the sidewalk's) and the edge lines' (2 mm above the
    road's) are folded into these two levels; the difference is far below a pixel. Dashes lie flush with the
    road and win over it (pybullet drew them z-fighting with the road, so parts of them showed as road).

    Across the street the ground is a function of y alone, read from 1 cm lookup tables; the junction, the
    dashes and the street's ends are then settled on the pixels they concern.
    """

    UPPER_Z = SIDEWALK_TOP_Z
    LOWER_Z = ROAD_TOP_Z
    CENTRE = NUM_CLASSES           # lookup codes settled afterwards: on the centre line (a dash or road by x),
    KERB = NUM_CLASSES + 1         # and a kerb's face (Sidewalks)
    _RES = 0.01
    _Y_MIN = -200.0
    _LUT_UP = _LUT_LOW = None

    def __init__(self, junction_x: float, dash_x) -> None:
        self.junction_x = float(junction_x)
        self.dash_x = np.sort(np.asarray(dash_x, dtype=np.float64).reshape(-1))
        self._dash_half = TEMPLATES["dash"].size[0]
        self._side_half = TEMPLATES["side_street"].size[0]
        if FlatGround._LUT_UP is None:
            FlatGround._LUT_UP, FlatGround._LUT_LOW = self._tables()

    @classmethod
    def _tables(cls) -> tuple[np.ndarray, np.ndarray]:
        ay = np.abs(cls._Y_MIN + cls._RES * (np.arange(int(round(-2 * cls._Y_MIN / cls._RES)) + 1) + 0.5))
        land = (ay >= ROAD_HALF_WIDTH) & (ay <= ROAD_HALF_WIDTH + SIDEWALK_WIDTH)
        up = np.where(land, SIDEWALKS, NONE).astype(np.uint8)
        low = np.where(land, cls.KERB, NONE).astype(np.uint8)
        low[ay < ROAD_HALF_WIDTH] = ROADS
        low[np.abs(ay - EDGE_LINE_Y) <= LINE_HALF_WIDTH] = ROADLINES
        low[ay <= LINE_HALF_WIDTH] = cls.CENTRE
        return up, low

    def classify(self, rays: np.ndarray, ex: float, ey: float, c: float, s: float, ratio: float,
                 reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Classes hit by downward rays from the eye (ex, ey), heading (cos, sin) = (c, s), that cross
        ``UPPER_Z`` at ``rays`` = (forward, left) (shape (2, n)) from the eye in the heading's frame, and
        ``LOWER_Z`` at ``ratio`` times that. ``reach`` bounds the rays' horizontal distance from the eye.
        Returns the class per ray (0, None: no ground), whether it was hit at ``UPPER_Z``, and the rays that
        hit a kerb's face with where (as a multiple of the distance to ``UPPER_Z``, between 1 and ``ratio``)."""
        inv = 1.0 / self._RES
        origin = (ey - self._Y_MIN) * inv
        lateral = np.dot((s * inv, c * inv), rays)          # y - ey at UPPER_Z, in table cells
        cell = lateral + origin
        up = self._LUT_UP.take(cell.astype(np.intp), mode="clip")
        cell = lateral * ratio
        cell += origin
        cls = self._LUT_LOW.take(cell.astype(np.intp), mode="clip")
        upper = up > 0
        np.copyto(cls, up, where=upper)

        x0, x1 = GROUND_X
        ends = ex - reach < x0 or ex + reach > x1            # near the ends of the street only
        junction = abs(self.junction_x - ex) <= reach + self._side_half
        if junction or ends:
            along = np.dot((c, -s), rays)                   # x - ex at UPPER_Z
            if junction:
                near = np.abs(along - (self.junction_x - ex)) <= self._side_half
                near &= upper
                cls[near] = ROADS
            if ends:
                x = ex + np.where(upper, along, ratio * along)
                cls[(x < x0) | (x > x1)] = NONE
        centre = (cls == self.CENTRE).nonzero()[0]
        if centre.size:
            x = ex + ratio * np.dot((c, -s), rays.take(centre, axis=1))
            n = self.dash_x.size
            if n:
                k = np.searchsorted(self.dash_x, x)
                gap = np.minimum(np.abs(x - self.dash_x[np.maximum(k - 1, 0)]),
                                 np.abs(x - self.dash_x[np.minimum(k, n - 1)]))
                cls[centre] = np.where(gap <= self._dash_half, ROADLINES, ROADS)
            else:
                cls[centre] = ROADS
        kerb = (cls == self.KERB).nonzero()[0]
        at = np.empty(0)
        if kerb.size:
            cls[kerb] = SIDEWALKS
            lat = lateral.take(kerb) * self._RES            # never 0: the ray crosses the kerb line
            side = np.where(ey + ratio * lat >= 0.0, ROAD_HALF_WIDTH, -ROAD_HALF_WIDTH)
            at = np.minimum(np.maximum((side - ey) / lat, 1.0), ratio)
        return cls, upper, kerb, at


class BodyPool:
    """The pybullet side of the scene: every body created once, then moved per episode and per frame.

    What TinyRenderer draws is controlled by colour alpha: pybullet skips a body with alpha 0 entirely (a
    parked body still costs its vertex work, about 4 us). Bodies the layout does not use, inactive actors and
    the flat ground (drawn by the camera itself, see ``FlatGround``) are hidden; ``show`` hides in-use bodies
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

        def make(cls: int, shape: str, size: tuple, pos=(0.0, 0.0, PARK_Z)) -> int:
            colour = list(PALETTE[cls] / 255.0) + [1.0]
            half = list(size) if shape == "box" else [size[0], size[0], size[1] / 2]
            vs = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=colour, physicsClientId=client)
            uid = p.createMultiBody(baseMass=0, baseVisualShapeIndex=vs, basePosition=list(pos),
                                    physicsClientId=client)
            if uid != len(rgba):
                raise RuntimeError("BodyPool needs a fresh pybullet client (body ids 0, 1, 2, ...)")
            self.uid_class[uid] = cls
            rgba.append(colour)
            radius.append(float(np.hypot(half[0], half[1])))
            height.append(float(half[2]))
            return uid

        fixed = [make(cls, "box", half, centre) for cls, half, centre in FIXED_BOXES]
        # Buildings: per template, (full height, uids) from the lowest to the tallest.
        self.buildings: dict[str, list[tuple[float, list[int]]]] = {}
        for name, tmpl in TEMPLATES.items():
            if tmpl.cls == BUILDINGS:
                hx, hy, _ = tmpl.size
                self.buildings[name] = [
                    (h, [make(tmpl.cls, "box", (hx, hy, h / 2)) for _ in range(k or tmpl.count)])
                    for h, k in zip(BUILDING_HEIGHTS, BUILDING_HEIGHT_COUNTS)]
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
        self.ground = FlatGround(0.5 * (SCENE_X[0] + SCENE_X[1]), [])
        # Per body: footprint centre and bounding radius, z range (for culling), in use, drawn (alpha 1).
        self.centre = np.zeros((n, 2))
        self.radius = np.array(radius)
        self.z = np.full((n, 2), PARK_Z)
        self.in_use = np.zeros(n, dtype=bool)
        self.shown = np.ones(n, dtype=bool)            # as created
        for uid in fixed:                               # fixed ground: in place, and in use, for ever
            _, _, centre_z = FIXED_BOXES[uid][2]
            self.centre[uid] = FIXED_BOXES[uid][2][:2]
            self.z[uid] = (centre_z - height[uid], centre_z + height[uid])
            self.in_use[uid] = True
        self._half_height = np.array(height)
        self._cullable = np.ones(n, dtype=bool)
        self._cullable[self.ground_uids] = False
        self._cullable[self.ego] = False
        self._cars = np.array(self.cars)
        self._peds = np.array(self.pedestrians)
        self.z[self._cars] = (0.0, 2.0 * self._car_half_height)          # where actors stand when active
        self.z[self._peds] = (SIDEWALK_HEIGHT, SIDEWALK_HEIGHT + 2.0 * self._ped_half_height)
        self.show(np.zeros(n, dtype=bool))

    # ------------------------------------------------------------------ placing
    def _move(self, uid: int, pos) -> None:
        self._p.resetBasePositionAndOrientation(uid, pos, (0.0, 0.0, 0.0, 1.0), physicsClientId=self.client)
        self.centre[uid] = pos[:2]
        h = self._half_height[uid]
        self.z[uid] = (pos[2] - h, pos[2] + h)

    def _building_spots(self, name: str, spots: list) -> dict[int, tuple]:
        """uid -> position for the layout's buildings of one template: the lowest free box that is tall enough."""
        top = TEMPLATES[name].size[2]               # the layout places the template's box: centre z = height - top
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
        self.ground = FlatGround(layout.junction_x, [s[0] for s in layout.placements.get("dash", [])])

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

    def place_ego(self, x: float, y: float, heading: float, visible: bool) -> None:
        h = 0.5 * heading
        pos = (x, y, self._car_half_height) if visible else (0.0, 0.0, PARK_Z)
        self._p.resetBasePositionAndOrientation(self.ego, pos, (0.0, 0.0, math.sin(h), math.cos(h)),
                                                physicsClientId=self.client)
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
