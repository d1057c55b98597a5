"""Off-screen segmentation camera (pybullet TinyRenderer, DIRECT mode).

The camera rides above the ego's roof, 0.5 m ahead of its centre at 1.6 m, pitched 8 degrees down. It sits
outside every body the ego can touch before an episode ends (TinyRenderer can hang with the eye inside a
body), and the ego itself has no body in the forward view.

The field of view (90 degrees by default) was chosen from a measurement: ``benchmarks/bench_env.py``
reports the share of test-bank scenarios whose hazard is visible at onset per TTC x speed cell.

Speed (``python -m benchmarks.bench_env --profile-only`` times each part; that module's docstring has the
profile). TinyRenderer draws every body in the world with a bounding-box rasteriser, so its cost is the number
of bodies (about 4 us each, even out of view) plus the screen area of every triangle's bounding box. Four
things keep a frame cheap (from ~3.2 ms to ~0.8 ms) while drawing the same scene:

* **The flat ground is drawn here, per pixel.** Road, sidewalks, kerbs, road lines and the side street are
  huge, thin triangles whose bounding boxes cover most of the screen (about 60 % of the original render
  time). The camera's height and pitch never change, so where each pixel's ray meets the two ground levels is
  fixed in the ego's frame and precomputed; per frame the hits are rotated to the ego's pose, classified by
  ``FlatGround`` and composited with TinyRenderer's depth buffer: the ground wins a pixel where it is
  nearer than what TinyRenderer drew there (the depth test TinyRenderer itself would have made). The ground's
  bodies stay in the world, hidden, as the reference (``analytic_ground=False`` draws them instead; a test
  compares the two: > 99.8 % of pixels agree, and the dashes, which pybullet drew z-fighting with the road,
  are now whole) and for the bird's-eye view.
* **Culling**: bodies not in use, and bodies provably outside the view frustum (a conservative test of each
  body's bounding cylinder against the near, far and side planes), are hidden with alpha 0, which pybullet
  skips entirely. Culling only removes bodies with no point in the frustum, so the frame is unchanged
  (``cull=False`` draws every body in use; a test compares the two).
* **Short building boxes** (``scene.BUILDING_HEIGHTS``): a building is buried < 3 m instead of up to 18 m.
* Only active actors are moved, and only bodies whose visibility changes are touched.

More pixels cost in proportion (``python -m benchmarks.bench_env --views``): the whole frame at 128×128 gives ~0.4×
the steps/s, at 256×256 ~0.1×, and a horizon band of the 90° width at 4× the pixels per degree (256×48) ~6× the
64×64 frame's render. Drawing road users pixel-conservatively in the 64×64 frame (``road_user_cover``) costs ~0.2 ms
(~0.7× the steps/s): no pixels are added, only the road users' outlines are projected (``SegmentationCamera``).
"""

from __future__ import annotations

import math

import numpy as np

from .scene import (
    EDGE_LINE_Y,
    GROUND_X,
    LANE_WIDTH,
    LINE_HALF_WIDTH,
    NONE,
    NUM_CLASSES,
    PALETTE,
    PEDESTRIANS,
    ROAD_HALF_WIDTH,
    ROAD_TOP_Z,
    ROADLINES,
    ROADS,
    SCENE_X,
    SIDEWALK_TOP_Z,
    SIDEWALK_WIDTH,
    SIDEWALKS,
    TEMPLATES,
    VEHICLES,
    StaticLayout,
)

EYE_FORWARD = 0.5
EYE_HEIGHT = 1.6
PITCH_DEG = 8.0
NEAR, FAR = 0.1, 70.0


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
    CENTRE = NUM_CLASSES  # lookup codes settled afterwards: on the centre line (a dash or road by x),
    KERB = NUM_CLASSES + 1  # and a kerb's face (Sidewalks)
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

    def classify(
        self, rays: np.ndarray, ex: float, ey: float, c: float, s: float, ratio: float, reach: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Classes hit by downward rays from the eye (ex, ey), heading (cos, sin) = (c, s), that cross
        ``UPPER_Z`` at ``rays`` = (forward, left) (shape (2, n)) from the eye in the heading's frame, and
        ``LOWER_Z`` at ``ratio`` times that. ``reach`` bounds the rays' horizontal distance from the eye.
        Returns the class per ray (0, None: no ground), whether it was hit at ``UPPER_Z``, and the rays that
        hit a kerb's face with where (as a multiple of the distance to ``UPPER_Z``, between 1 and ``ratio``)."""
        inv = 1.0 / self._RES
        origin = (ey - self._Y_MIN) * inv
        lateral = np.dot((s * inv, c * inv), rays)  # y - ey at UPPER_Z, in table cells
        cell = lateral + origin
        up = self._LUT_UP.take(cell.astype(np.intp), mode="clip")
        cell = lateral * ratio
        cell += origin
        cls = self._LUT_LOW.take(cell.astype(np.intp), mode="clip")
        upper = up > 0
        np.copyto(cls, up, where=upper)

        x0, x1 = GROUND_X
        ends = ex - reach < x0 or ex + reach > x1  # near the ends of the street only
        junction = abs(self.junction_x - ex) <= reach + self._side_half
        if junction or ends:
            along = np.dot((c, -s), rays)  # x - ex at UPPER_Z
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
                gap = np.minimum(
                    np.abs(x - self.dash_x[np.maximum(k - 1, 0)]), np.abs(x - self.dash_x[np.minimum(k, n - 1)])
                )
                cls[centre] = np.where(gap <= self._dash_half, ROADLINES, ROADS)
            else:
                cls[centre] = ROADS
        kerb = (cls == self.KERB).nonzero()[0]
        at = np.empty(0)
        if kerb.size:
            cls[kerb] = SIDEWALKS
            lat = lateral.take(kerb) * self._RES  # never 0: the ray crosses the kerb line
            side = np.where(ey + ratio * lat >= 0.0, ROAD_HALF_WIDTH, -ROAD_HALF_WIDTH)
            at = np.minimum(np.maximum((side - ey) / lat, 1.0), ratio)
        return cls, upper, kerb, at


class CrossroadsGround:
    """The flat ground of a four-way junction (family kim) as plain geometry, drawn per pixel like ``FlatGround``.

    Two roads of ``half_width`` each side of their centre lines cross at x = ``junction_x``: the main road along
    x (the ego's) and the cross road along y. Everything else is land at the sidewalk level (Sidewalks, as the
    street's land behind its sidewalks is). On the roads, outside the junction's box: a solid centre line, solid
    edge lines 0.2 m inside the kerbs, dashed dividers (3 m of every 6 m) between lanes of ``lane_width``, and a
    0.4 m stop line across each approach's own lanes (right-hand traffic), 0.5 m before the crossing road's edge.
    Kerb faces are Sidewalks at the depth where the ray crosses the kerb line, as in ``FlatGround``. There are no
    ground bodies to compare with: ``analytic_ground=False`` draws the street's hidden boxes instead.
    """

    UPPER_Z = SIDEWALK_TOP_Z
    LOWER_Z = ROAD_TOP_Z
    DASH_PERIOD_M, DASH_M = 6.0, 3.0
    STOP_LINE_M = (0.5, 0.9)  # from the crossing road's edge, metres

    def __init__(self, junction_x: float, half_width: float, lane_width: float = LANE_WIDTH) -> None:
        if not half_width > 0.0:
            raise ValueError(f"crossroads half_width={half_width!r} must be positive")
        self.junction_x = float(junction_x)
        self.half_width = float(half_width)
        self.dividers = lane_width * np.arange(1, int(round(half_width / lane_width)))

    def _land(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        hw = self.half_width
        return (np.abs(y) >= hw) & (np.abs(x - self.junction_x) >= hw)

    def _markings(self, across: np.ndarray, along: np.ndarray) -> np.ndarray:
        """Road lines of one road at ``across`` from its centre line and ``along`` from the junction's centre, for
        points on that road outside the junction's box. Traffic keeps right: the lanes at across < 0 approach the
        junction from along < 0."""
        hw, w = self.half_width, LINE_HALF_WIDTH
        a = np.abs(across)
        line = (a <= w) | (np.abs(a - (hw - 0.2)) <= w)
        if self.dividers.size:
            dash = np.mod(along, self.DASH_PERIOD_M) < self.DASH_M
            line |= dash & (np.abs(a[:, None] - self.dividers[None, :]) <= w).any(axis=1)
        near, far = hw + self.STOP_LINE_M[0], hw + self.STOP_LINE_M[1]
        approach = np.where(across < 0.0, -along, along)
        return line | ((approach >= near) & (approach <= far))

    def _lines(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Which road points (x, y) carry a road line."""
        jx, hw = self.junction_x, self.half_width
        main = (np.abs(y) < hw) & (np.abs(x - jx) > hw)
        cross = (np.abs(x - jx) < hw) & (np.abs(y) > hw)
        lines = np.zeros(x.shape, dtype=bool)
        lines[main] = self._markings(y[main], x[main] - jx)
        lines[cross] = self._markings(-(x[cross] - jx), y[cross])
        return lines

    def at_points(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The ground's class at world points (x, y) seen from straight above (the bird's-eye view)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        cls = np.where(self._land(x, y), SIDEWALKS, ROADS).astype(np.uint8)
        cls[(cls == ROADS) & self._lines(x, y)] = ROADLINES
        return cls

    def classify(
        self, rays: np.ndarray, ex: float, ey: float, c: float, s: float, ratio: float, reach: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """As ``FlatGround.classify``: the class per ray, whether it was hit at ``UPPER_Z``, the rays that hit a
        kerb's face and where (as a multiple of the distance to ``UPPER_Z``, between 1 and ``ratio``)."""
        along = np.dot((c, -s), rays)  # x - ex at UPPER_Z
        lat = np.dot((s, c), rays)  # y - ey at UPPER_Z
        xu, yu = ex + along, ey + lat
        xl, yl = ex + ratio * along, ey + ratio * lat
        upper = self._land(xu, yu)
        cls = np.where(upper, SIDEWALKS, ROADS).astype(np.uint8)
        low = ~upper
        kerb = (low & self._land(xl, yl)).nonzero()[0]
        cls[kerb] = SIDEWALKS
        road = (low & ~self._land(xl, yl)).nonzero()[0]
        cls[road[self._lines(xl.take(road), yl.take(road))]] = ROADLINES
        jx, hw = self.junction_x, self.half_width
        at = np.empty(0)
        if kerb.size:
            # The ray enters the land when both |y| >= hw and |x - jx| >= hw hold: the later of the two crossings.
            with np.errstate(divide="ignore", invalid="ignore"):
                ay, ax = lat.take(kerb), along.take(kerb)
                ty = np.where(np.abs(yu.take(kerb)) >= hw, 1.0, (np.sign(yl.take(kerb)) * hw - ey) / ay)
                tx = np.where(np.abs(xu.take(kerb) - jx) >= hw, 1.0, (jx + np.sign(xl.take(kerb) - jx) * hw - ex) / ax)
            at = np.clip(np.maximum(ty, tx), 1.0, ratio)
        return cls, upper, kerb, at


class SegmentationCamera:
    """One camera at the ego's fixed eye pose; ``render`` gives its (size, size) class map.

    Two ways of drawing road users (pedestrians and vehicles) more faithfully than TinyRenderer's one sample per pixel,
    for views that must not lose a pedestrian narrower than a pixel (docs/design.md §3, "Views"):

    * ``road_user_cover``: a pixel shows a road user wherever the road user's box covers any part of it, unless
      something nearer is drawn at all four of the pixel's corners (conservative rasterisation; a pedestrian that
      steps out from behind a parked car by a fraction of a pixel shows). It is the limit of rendering at k×
      and pooling as below, for k -> infinity, at the cost of projecting the boxes in view (~0.2 ms per frame).
    * ``supersample=k``: render at k× the size and pool each k×k block: a pedestrian in any sub-pixel wins, then a
      vehicle; otherwise the sub-pixel at the coarse pixel's own sample point (so the rest of the frame is the
      plain render's). The reference for the cover; it costs the k²-larger render.
    """

    def __init__(
        self,
        client: int,
        pool,
        size: int = 64,
        fov_deg: float = 90.0,
        road_user_cover: bool = False,
        supersample: int = 1,
    ):
        import pybullet as p

        self._p = p
        self.client = client
        self.pool = pool
        self.lut = pool.lut
        self.size = size
        self.projection = p.computeProjectionMatrixFOV(fov_deg, 1.0, NEAR, FAR, physicsClientId=client)
        proj = np.array(self.projection, dtype=np.float64).reshape(4, 4).T  # pybullet: column-major
        self._px, self._py = proj[0, 0], proj[1, 1]
        # TinyRenderer's own reading of the clip planes from the matrix.
        self.near = proj[2, 3] / (proj[2, 2] - 1.0)
        self.far = proj[2, 3] / (proj[2, 2] + 1.0)
        self.cull = True
        self.analytic_ground = True
        self.road_user_cover = bool(road_user_cover)
        if int(supersample) < 1:
            raise ValueError(f"supersample={supersample!r} must be a positive integer")
        self.supersample = int(supersample)
        self._fine = (
            SegmentationCamera(client, pool, size * self.supersample, fov_deg, road_user_cover=False)
            if self.supersample > 1
            else None
        )
        self.last_uids = np.full((size, size), -1, dtype=np.int32)
        self.ground = FlatGround(0.5 * (SCENE_X[0] + SCENE_X[1]), [])
        self._prepare_ground_rays()

    def set_layout(self, layout: StaticLayout) -> None:
        """The flat ground of this episode's layout: the street (its junction and centre-line dashes) or a four-way
        junction."""
        if layout.crossroads_half_width > 0.0:
            self.ground = CrossroadsGround(layout.junction_x, layout.crossroads_half_width)
        else:
            self.ground = FlatGround(layout.junction_x, [s[0] for s in layout.placements.get("dash", [])])
        if self._fine is not None:
            self._fine.set_layout(layout)

    def _view(self, x: float, y: float, heading: float) -> list:
        c, s = math.cos(heading), math.sin(heading)
        eye = (x + EYE_FORWARD * c, y + EYE_FORWARD * s, EYE_HEIGHT)
        drop = math.tan(math.radians(PITCH_DEG)) * 10.0
        target = (eye[0] + 10.0 * c, eye[1] + 10.0 * s, EYE_HEIGHT - drop)
        return self._p.computeViewMatrix(eye, target, (0.0, 0.0, 1.0), physicsClientId=self.client)

    # ------------------------------------------------------------------ the flat ground, per pixel
    def _prepare_ground_rays(self) -> None:
        """Where each pixel's ray meets the ground levels, in the ego's frame (eye at the origin, heading 0)."""
        n = self.size
        view = np.array(self._view(-EYE_FORWARD, 0.0, 0.0), dtype=np.float64).reshape(4, 4).T
        rot = view[:3, :3]  # world -> eye
        # TinyRenderer samples pixel (col, row) at screen point (col, n - 1 - row) (it flips rows afterwards),
        # i.e. at NDC (2 col / n - 1, 2 (n - 1 - row) / n - 1).
        ndc = 2.0 * np.arange(n) / n - 1.0
        eye_dir = np.empty((n, n, 3))
        eye_dir[..., 0] = ndc[None, :] / self._px
        eye_dir[..., 1] = ndc[::-1][:, None] / self._py
        eye_dir[..., 2] = -1.0  # so the ray parameter is the eye depth
        world = eye_dir @ rot  # rows: rot.T @ d
        dz = world[..., 2].reshape(-1)
        with np.errstate(divide="ignore"):
            t_up = np.where(dz < 0.0, (FlatGround.UPPER_Z - EYE_HEIGHT) / dz, np.inf)
            t_low = np.where(dz < 0.0, (FlatGround.LOWER_Z - EYE_HEIGHT) / dz, np.inf)
        idx = np.flatnonzero(t_up <= self.far)
        flat = world.reshape(-1, 3)[idx, :2] * t_up[idx, None]  # (forward, left) from the eye at UPPER_Z
        self._g_idx = idx
        self._g_t_up = t_up[idx]
        self._g_rays = np.ascontiguousarray(flat.T)  # (2, n): forward, left
        self._g_depth_up = self._depth_value(t_up[idx])
        self._g_depth_low = self._depth_value(t_low[idx])
        self._g_ratio = (FlatGround.LOWER_Z - EYE_HEIGHT) / (FlatGround.UPPER_Z - EYE_HEIGHT)
        self._g_reach = self._g_ratio * float(np.hypot(flat[:, 0], flat[:, 1]).max(initial=0.0))

    def _depth_value(self, d: np.ndarray) -> np.ndarray:
        """Eye depth -> the value in pybullet's depth buffer (float32; 1 at the far plane, > 1 beyond)."""
        n, f = self.near, self.far
        return (f * (d - n) / ((f - n) * d)).astype(np.float32)

    def _composite_ground(self, uids: np.ndarray, depth: np.ndarray, x: float, y: float, heading: float) -> None:
        """Write the ground's uid into ``uids`` wherever the ground is nearer than what TinyRenderer drew."""
        d_obj = depth.reshape(-1).take(self._g_idx)
        cand = (d_obj > self._g_depth_up).nonzero()[0]  # the ground can only win where the object is further
        if cand.size == 0:
            return
        c, s = math.cos(heading), math.sin(heading)
        cls, upper, kerb, at = self.ground.classify(
            self._g_rays.take(cand, axis=1),
            x + EYE_FORWARD * c,
            y + EYE_FORWARD * s,
            c,
            s,
            self._g_ratio,
            self._g_reach,
        )
        # Hits at the upper level are nearer than the object by the choice of ``cand``; the others are tested.
        d_obj = d_obj.take(cand)
        d_low = self._g_depth_low.take(cand)
        if kerb.size:
            d_low[kerb] = self._depth_value(self._g_t_up.take(cand.take(kerb)) * at)
        win = d_low < d_obj
        win |= upper
        win &= cls > 0
        win = win.nonzero()[0]
        uids.reshape(-1)[self._g_idx.take(cand.take(win))] = self.pool.ground_uid.take(cls.take(win))

    # ------------------------------------------------------------------ culling
    def _visible(self, x: float, y: float, heading: float) -> np.ndarray:
        """Bodies in use that may have a point in the view frustum (conservative: bounding cylinders)."""
        pool = self.pool
        want = pool.cullable_in_use()
        if not self.cull:
            return want
        c, s = math.cos(heading), math.sin(heading)
        dx = pool.centre[:, 0] - (x + EYE_FORWARD * c)
        dy = pool.centre[:, 1] - (y + EYE_FORWARD * s)
        fwd = dx * c + dy * s
        lat = np.abs(dy * c - dx * s) - pool.radius
        cp, sp = math.cos(math.radians(PITCH_DEG)), math.sin(math.radians(PITCH_DEG))
        # Eye depth of a point (forward f, height h above the eye): f cos(pitch) - h sin(pitch).
        d_max = (fwd + pool.radius) * cp - (pool.z[:, 0] - EYE_HEIGHT) * sp
        d_min = (fwd - pool.radius) * cp - (pool.z[:, 1] - EYE_HEIGHT) * sp
        return want & (d_max >= self.near) & (d_min <= self.far) & (lat <= d_max / self._px)

    # ------------------------------------------------------------------ frames
    def _image(self, view, size: int, projection) -> tuple[np.ndarray, np.ndarray]:
        _, _, _, depth, seg = self._p.getCameraImage(
            size, size, view, projection, renderer=self._p.ER_TINY_RENDERER, physicsClientId=self.client
        )
        # pybullet already keeps only the low 24 bits (the body uid) of object pixels; background is -1.
        return np.asarray(seg, dtype=np.int32).reshape(size, size), np.asarray(depth).reshape(size, size)

    def render_uids(self, x: float, y: float, heading: float) -> np.ndarray:
        """Body-uid frame (size, size) int32 seen from the ego pose; -1 is background."""
        if self._fine is not None:
            return self._pool_blocks(self._fine.render_uids(x, y, heading))
        want = self._visible(x, y, heading)
        if not self.analytic_ground:
            want[self.pool.ground_uids] = True
        self.pool.show(want)
        view = self._view(x, y, heading)
        uids, depth = self._image(view, self.size, self.projection)
        if self.analytic_ground:
            self._composite_ground(uids, depth, x, y, heading)
        if self.road_user_cover:
            self._cover_road_users(uids, depth, view, want)
        return uids

    # ------------------------------------------------------------------ road users, pixel-conservative
    def _pool_blocks(self, fine: np.ndarray) -> np.ndarray:
        """(k n, k n) uids -> (n, n): per k×k block a pedestrian, else a vehicle, else the coarse sample's sub-pixel
        (row k - 1, column 0 of the block: TinyRenderer samples pixel (col, row) at screen (col, n - 1 - row))."""
        n, k = self.size, self.supersample
        blocks = fine.reshape(n, k, n, k)
        out = blocks[:, k - 1, :, 0].copy()
        cls = self.lut[blocks + 1]
        for c in (VEHICLES, PEDESTRIANS):  # pedestrians last: they win a block that holds both
            hit = np.where(cls == c, blocks, -1).max(axis=(1, 3))
            np.copyto(out, hit, where=hit >= 0)
        return out

    def _cover_road_users(self, uids: np.ndarray, depth: np.ndarray, view, drawn: np.ndarray) -> None:
        """Mark every pixel that a drawn road user's box covers in part, unless something drawn at each of the pixel's
        four corners is nearer than the box's nearest corner (the ground never hides a road user)."""
        pool, n = self.pool, self.size
        bodies = pool.road_users[drawn[pool.road_users]]
        if bodies.size == 0:
            return
        corners = _box_corners(pool.centre[bodies], pool.z[bodies], pool.half_extents[bodies], pool.heading[bodies])
        v = np.array(view, dtype=np.float64).reshape(4, 4).T
        eye = corners @ v[:3, :3].T + v[:3, 3]  # (bodies, 8, 3); the camera looks down -z
        dist = -eye[..., 2]
        in_front = (dist > self.near).all(axis=1)  # a box reaching behind the near plane fills the frame anyway
        # Screen units: u = column (pixel col spans [col, col + 1)), w = row (pixel row spans [row, row + 1)).
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (self._px * eye[..., 0] / dist + 1.0) * (0.5 * n)
            w = n - (self._py * eye[..., 1] / dist + 1.0) * (0.5 * n)
        # A pixel's sample point is its bottom-left corner, so the samples of the pixel and of its right, upper and
        # upper-right neighbours are its four corners: the nearest depth drawn at the farthest of them.
        padded = np.pad(depth, ((1, 0), (0, 1)), mode="edge")
        corners_depth = np.maximum(
            np.maximum(padded[1:, :-1], padded[1:, 1:]), np.maximum(padded[:-1, :-1], padded[:-1, 1:])
        ).reshape(-1)
        flat_uids = uids.reshape(-1)
        # Vehicles, then pedestrians (who win a pixel both cover), each from the farthest to the nearest, so that of
        # two road users covering one pixel the nearer shows.
        order = np.lexsort((-dist.min(axis=1), self.lut[bodies + 1] == PEDESTRIANS))
        for b in order[in_front[order]]:
            c0, c1 = max(int(math.floor(u[b].min())), 0), min(int(math.floor(u[b].max())), n - 1)
            r0, r1 = max(int(math.floor(w[b].min())), 0), min(int(math.floor(w[b].max())), n - 1)
            if c0 > c1 or r0 > r1:
                continue
            cols = np.tile(np.arange(c0, c1 + 1), r1 - r0 + 1)
            rows = np.repeat(np.arange(r0, r1 + 1), c1 - c0 + 1)
            inside = _squares_meet_box(cols, rows, np.stack([u[b], w[b]], 1))
            pix = (rows * n + cols)[inside]
            near = self._depth_value(np.array([dist[b].min()]))[0]
            uid = bodies[b]
            seen = (corners_depth.take(pix) >= near) | (flat_uids.take(pix) == uid)
            flat_uids[pix[seen]] = uid

    def render(self, x: float, y: float, heading: float) -> np.ndarray:
        """Class-id frame (size, size) uint8 seen from the ego pose."""
        self.last_uids = self.render_uids(x, y, heading)
        return self.lut[self.last_uids + 1]

    def birds_eye(self, x: float, y: float, heading: float, size: int = 128, span: float = 60.0) -> np.ndarray:
        """Top-down uid map centred ahead of the ego, forward pointing up the image (for people, not speed)."""
        p = self._p
        c, s = math.cos(heading), math.sin(heading)
        centre = (x + 0.3 * span * c, y + 0.3 * span * s, 0.0)
        height = 150.0
        fov = math.degrees(2.0 * math.atan(0.5 * span / height))
        view = p.computeViewMatrix((centre[0], centre[1], height), centre, (c, s, 0.0), physicsClientId=self.client)
        proj = p.computeProjectionMatrixFOV(fov, 1.0, 1.0, 400.0, physicsClientId=self.client)
        if not isinstance(self.ground, CrossroadsGround):
            self.pool.show_everything(ground=True)  # the street's ground bodies are its reference
            return self._image(view, size, proj)[0]
        # A junction has no ground bodies: what shows no body is its ground at the pixel's point (forward up the
        # image, left to the left; the 1 m of relief is far below a pixel from 150 m).
        self.pool.show_everything(ground=False)
        uids = self._image(view, size, proj)[0]
        ndc = (np.arange(size) + 0.5) / size * 2.0 - 1.0
        forward, left = -ndc[:, None] * 0.5 * span, -ndc[None, :] * 0.5 * span
        gx, gy = centre[0] + forward * c - left * s, centre[1] + forward * s + left * c
        empty = uids < 0
        uids[empty] = self.pool.ground_uid.take(self.ground.at_points(gx[empty], gy[empty]))
        return uids


def _box_corners(centre: np.ndarray, z: np.ndarray, half: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(B, 8, 3) world corners of boxes: footprint centre (B, 2), z range (B, 2), half extents (B, 3), heading (B,)."""
    sx = np.array([1, 1, -1, -1, 1, 1, -1, -1], dtype=np.float64)
    sy = np.array([1, -1, 1, -1, 1, -1, 1, -1], dtype=np.float64)
    top = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    dx, dy = sx * half[:, :1], sy * half[:, 1:2]
    out = np.empty((len(centre), 8, 3))
    out[..., 0] = centre[:, :1] + dx * c - dy * s
    out[..., 1] = centre[:, 1:2] + dx * s + dy * c
    out[..., 2] = z[:, top]
    return out


# The 12 edges of a box, as pairs of ``_box_corners`` indices: the outline of its projection is made of some of them.
_BOX_EDGES = np.array([(0, 1), (1, 3), (3, 2), (2, 0), (4, 5), (5, 7), (7, 6), (6, 4), (0, 4), (1, 5), (2, 6), (3, 7)])


def _squares_meet_box(cols: np.ndarray, rows: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Whether each unit square [col, col + 1] x [row, row + 1] meets the convex outline of a box's eight projected
    ``corners`` (8, 2). Separating axes: the squares' own axes are settled by the caller's bounding box; the outline's
    edges are projected box edges, so the normals of all twelve hold every axis that can separate (an extra axis
    separates only what is apart)."""
    edge = corners[_BOX_EDGES[:, 1]] - corners[_BOX_EDGES[:, 0]]
    nx, ny = edge[:, 1], -edge[:, 0]
    along = corners @ np.stack([nx, ny])  # (8, 12): each corner along each normal
    low, high = along.min(axis=0)[:, None], along.max(axis=0)[:, None]
    base = np.multiply.outer(nx, cols) + np.multiply.outer(ny, rows)
    square_low = base + (np.minimum(nx, 0.0) + np.minimum(ny, 0.0))[:, None]
    square_high = base + (np.maximum(nx, 0.0) + np.maximum(ny, 0.0))[:, None]
    return ((square_high >= low - 1e-9) & (square_low <= high + 1e-9)).all(axis=0)


def colorize(classes: np.ndarray) -> np.ndarray:
    """Class ids -> RGB with the CARLA palette."""
    return PALETTE[np.asarray(classes, dtype=np.intp)]
