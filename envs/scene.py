"""The static urban street as data: class ids, road geometry and the per-episode layout (numpy only).

World frame: x along the main street (the ego drives towards +x in the right-hand lane), y to the left,
z up, metres. The road is two 3.5 m lanes (ego lane centred at y=-1.75, oncoming at +1.75), with
sidewalks to |y|=6.5 and buildings set back behind them. One junction with a side street crosses the
street; a crossing hazard car comes out of it.

Every episode re-randomises the layout from the scenario seed (building setbacks, heights and spacing, poles,
signs, trees, fences, walls, bins, the junction position): ``sample_layout`` says where each kind of body goes.
The pybullet side (``envs/bodies.py``) realises it by moving pooled bodies; the camera (``envs/camera.py``)
draws the flat ground per pixel from the same geometry.

Collision footprints are kept here as plain arrays (axis-aligned rectangles and circles in the x-y plane):
the collision model (``envs.geometry``) is exact 2D geometry in numpy, so the camera-off mode needs no
pybullet at all and camera on/off give identical outcomes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CLASS_NAMES = (
    "None",
    "Buildings",
    "Fences",
    "Other",
    "Pedestrians",
    "Poles",
    "RoadLines",
    "Roads",
    "Sidewalks",
    "Vegetation",
    "Vehicles",
    "Walls",
    "TrafficSigns",
)
NUM_CLASSES = len(CLASS_NAMES)
(
    NONE,
    BUILDINGS,
    FENCES,
    OTHER,
    PEDESTRIANS,
    POLES,
    ROADLINES,
    ROADS,
    SIDEWALKS,
    VEGETATION,
    VEHICLES,
    WALLS,
    TRAFFICSIGNS,
) = range(NUM_CLASSES)

# CARLA's Cityscapes-style palette, so frames look like the paper's Fig. 4.
PALETTE = np.array(
    [
        (0, 0, 0),
        (70, 70, 70),
        (190, 153, 153),
        (250, 170, 160),
        (220, 20, 60),
        (153, 153, 153),
        (157, 234, 50),
        (128, 64, 128),
        (244, 35, 232),
        (107, 142, 35),
        (0, 0, 142),
        (102, 102, 156),
        (220, 220, 0),
    ],
    dtype=np.uint8,
)

LANE_WIDTH = 3.5
EGO_LANE_Y = -1.75
ONCOMING_LANE_Y = 1.75
ROAD_HALF_WIDTH = 3.5
SIDEWALK_OUTER = 6.5
SIDEWALK_HEIGHT = 0.15
SCENE_X = (-40.0, 330.0)
JUNCTION_HALF_WIDTH = 6.0  # half the side street's width; buildings keep clear of it
PARK_Z = -60.0  # where unused pool bodies wait, far below the ground


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
GROUND_X = (_X_MID - _X_HALF, _X_MID + _X_HALF)  # the ground's extent along the street
SIDEWALK_WIDTH = 40.0  # sidewalk boxes reach |y| = 3.5 + 40 (the land behind them)
ROAD_TOP_Z = 0.01
SIDEWALK_TOP_Z = SIDEWALK_HEIGHT - 0.01
LINE_HALF_WIDTH = 0.08
EDGE_LINE_Y = ROAD_HALF_WIDTH - 0.2
FIXED_BOXES = (
    (ROADS, (_X_HALF, ROAD_HALF_WIDTH, ROAD_TOP_Z), (_X_MID, 0.0, 0.0)),  # carriageway
    (
        SIDEWALKS,
        (_X_HALF, SIDEWALK_WIDTH / 2, SIDEWALK_HEIGHT / 2),
        (_X_MID, ROAD_HALF_WIDTH + SIDEWALK_WIDTH / 2, SIDEWALK_TOP_Z - SIDEWALK_HEIGHT / 2),
    ),
    (
        SIDEWALKS,
        (_X_HALF, SIDEWALK_WIDTH / 2, SIDEWALK_HEIGHT / 2),
        (_X_MID, -ROAD_HALF_WIDTH - SIDEWALK_WIDTH / 2, SIDEWALK_TOP_Z - SIDEWALK_HEIGHT / 2),
    ),
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
BUILDING_HEIGHT_COUNTS = (6, 6, 6, 6, 6, None)  # None: the template's count


@dataclass
class StaticLayout:
    """Where every pooled body goes this episode, and the obstacles the ego can crash into."""

    junction_x: float
    placements: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)
    rects: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))  # cx, cy, hx, hy, class
    circles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # cx, cy, r, class
    crossroads_half_width: float = 0.0
    """0: the street and its side street (``camera.FlatGround``). Positive: the ground is a four-way junction at
    ``junction_x`` of two roads this wide each side of their centre lines (family kim; ``camera.CrossroadsGround``)"""


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
            placed[name].append((cx, cy, height - hz))  # sunk so that ``height`` shows above ground
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
