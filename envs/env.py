"""``UrbanCollision-v0``: the imminent-collision gymnasium environment.

Spaces and timing (docs/design.md §3):

* step ``step_s`` (default 1/15 s, the paper's 15 FPS; the peers' 0.1 s is a setting), dynamics and collisions
  sub-stepped ``substeps`` times per step;
* action ``Box(-1, 1, (2,))`` = [steer, throttle/brake]: steer -1..1 is maximum left..maximum right;
  throttle/brake -1..0 asks for 9.8..0 m/s^2 of deceleration, 0..1 for up to ``VehicleParams.max_accel``.
  [0, 0] holds the current speed, the constant-velocity motion TTC is defined by;
* observation ``Dict(seg=Box(0, 12, (S, S), uint8), speed=Box(0, 40, (1,), float32))``; with
  ``camera=False`` the segmentation frame is all zeros and no pybullet client is created.

Episodes end (``terminated``) on a crash with a car or a static object, or when the ego leaves the scene.
They are truncated at ``min(max_episode_s, ttc + horizon_after_ttc_s)``; pass ``horizon_after_ttc_s=None``
for data collection (15 s). Stopping does not end an episode: a stopped car can still be hit.

``info`` on every step: ``collisions`` registered this step (kind, participant id, impact speed, delta-v of
each car, injury probability per participant, people involved), ``reward_<name>`` for every registered reward
(``envs.rewards``: ``reward_r1``, ``reward_r2``, ...), the ego state
(``x``, ``y``, ``heading``, ``speed``, ``steer_angle``, ``lane_offset``) and ``lane_departure``. On the last step
``info["outcome"]`` holds the paper's section IV-C metrics for the episode.
"""

from __future__ import annotations

import dataclasses
import math

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from . import crashes, families, geometry
from .actors import PEDESTRIAN_HALF_SIZE, PEDESTRIAN_RADIUS, Actors, build_actors
from .rewards import REGISTRY, StepContext, step_rewards
from .scenario import ScenarioSpec, sample_scenario
from .scene import EGO_LANE_Y, LANE_WIDTH, NUM_CLASSES, SCENE_X, StaticLayout, sample_layout
from .vehicle import VehicleParams, VehicleState, integrate

DT = 1.0 / 15.0
MAX_SPEED_OBS = 40.0
HORIZON_AFTER_TTC_S = 3.0  # the env's defaults for an episode's length (``horizon_steps``)
MAX_EPISODE_S = 15.0
APART_MARGIN_M = 0.01  # metres: see _prepare_static


def horizon_steps(
    ttc: float,
    step_s: float = DT,
    horizon_after_ttc_s: float | None = HORIZON_AFTER_TTC_S,
    max_episode_s: float = MAX_EPISODE_S,
) -> int:
    """The steps after which an episode of the paper's family is truncated: ``min(max_episode_s, ttc +
    horizon_after_ttc_s)`` seconds (``max_episode_s`` when ``horizon_after_ttc_s`` is None), rounded up to whole
    steps of ``step_s``. Defaults: the env's."""
    after = horizon_after_ttc_s
    return steps_in(max_episode_s if after is None else min(max_episode_s, ttc + after), step_s)


def steps_in(horizon_s: float, step_s: float) -> int:
    """``horizon_s`` seconds in whole steps of ``step_s``, rounded up (at least one)."""
    return max(1, int(math.ceil(horizon_s / step_s - 1e-9)))


def _copy_actors(a: Actors) -> Actors:
    """A copy whose arrays are independent of ``a``'s (actors move and get hit in place)."""
    return dataclasses.replace(
        a,
        **{
            f.name: getattr(a, f.name).copy()
            for f in dataclasses.fields(a)
            if isinstance(getattr(a, f.name), np.ndarray)
        },
    )


class UrbanCollisionEnv(gym.Env):
    """See the module docstring. Keyword arguments are the env config (``conf/env/urban.yaml``).

    camera: render the segmentation frame (False: zeros, for scripted evaluation and planners).
    image_size, fov_deg: the camera. road_user_cover, supersample: how the camera draws road users narrower than a
    pixel (``camera.SegmentationCamera``; the views of docs/design.md §3). tele_fov_deg: a second, narrow camera at
    the same pose (obs ``seg_tele``; None: none), so that a pedestrian 20-35 m ahead covers tens of pixels instead
    of a few. reward: 'r1' or 'r2'.
    horizon_after_ttc_s: agent-episode length after the TTC (None: ``max_episode_s``). mu: tyre-road friction.
    occupants_per_car: people per car.
    lateral_exit_m: metres from the street's centre line (|y|) beyond which the episode ends as ``left_scene``; the
    default 25 m lies past every static body of the paper's street, which reach 20.5 m (a huge value keeps the
    episode going, to see what leaving the scene would have cost).
    ego_mass, car_mass: kg, for delta-v. substeps: collision/dynamics sub-steps per step.
    step_s: seconds per step (``DT`` = 1/15 by default); planners and evaluation read it from the env.
    family: the scenario family ``reset()`` samples when no scenario is given (``porav``, the paper's; ``chae``,
    ``envs/chae.py``); ``reset(options={"scenario": spec})`` takes a spec of any family.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 15}

    def __init__(
        self,
        camera: bool = True,
        image_size: int = 64,
        fov_deg: float = 90.0,
        tele_fov_deg: float | None = None,
        road_user_cover: bool = False,
        supersample: int = 1,
        reward: str = "r2",
        horizon_after_ttc_s: float | None = HORIZON_AFTER_TTC_S,
        max_episode_s: float = MAX_EPISODE_S,
        mu: float = 1.0,
        occupants_per_car: int = 1,
        ego_mass: float = 1500.0,
        car_mass: float = 1500.0,
        substeps: int = 8,
        render_mode: str | None = None,
        step_s: float = DT,
        family: str = "porav",
        family_options: dict | None = None,
        lateral_exit_m: float = 25.0,
    ):
        checks = {
            "image_size": image_size >= 8,
            "fov_deg": 10.0 <= fov_deg <= 170.0,
            "tele_fov_deg": tele_fov_deg is None or 10.0 <= tele_fov_deg <= 170.0,
            "supersample": int(supersample) == supersample and 1 <= supersample <= 8,
            "mu": mu > 0.0,
            "max_episode_s": max_episode_s > 0.0,
            "occupants_per_car": occupants_per_car >= 1,
            "ego_mass": ego_mass > 0.0,
            "car_mass": car_mass > 0.0,
            "substeps": substeps >= 1,
            "step_s": 0.0 < step_s <= 0.5,
            "family": family in families.names(),
            "horizon_after_ttc_s": horizon_after_ttc_s is None or horizon_after_ttc_s > 0.0,
            "reward": reward in REGISTRY,
            "render_mode": render_mode in (None, "rgb_array"),
            "lateral_exit_m": lateral_exit_m > 0.0,
        }
        for key, ok in checks.items():
            if not ok:
                raise ValueError(f"env config {key}={locals()[key]!r} is invalid")
        self.camera, self.image_size, self.fov_deg = bool(camera), int(image_size), float(fov_deg)
        self.tele_fov_deg = None if tele_fov_deg is None else float(tele_fov_deg)
        self.road_user_cover, self.supersample = bool(road_user_cover), int(supersample)
        self.reward_name = reward
        self.horizon_after_ttc_s, self.max_episode_s = horizon_after_ttc_s, float(max_episode_s)
        self.occupants_per_car = int(occupants_per_car)
        self.ego_mass, self.car_mass = float(ego_mass), float(car_mass)
        self.substeps = int(substeps)
        self.step_s = float(step_s)
        self.family = family
        self.family_options = dict(family_options or {})  # keyword arguments of the family module's build()
        self.render_mode = render_mode
        self.lateral_exit_m = float(lateral_exit_m)
        self.params = VehicleParams(mu=float(mu), mass=float(ego_mass))

        s = self.image_size
        views = {
            "seg": spaces.Box(0, NUM_CLASSES - 1, (s, s), np.uint8),
            "speed": spaces.Box(0.0, MAX_SPEED_OBS, (1,), np.float32),
        }
        if self.tele_fov_deg is not None:
            views["seg_tele"] = spaces.Box(0, NUM_CLASSES - 1, (s, s), np.uint8)
        self.observation_space = spaces.Dict(views)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

        self._client = None
        self._pool = None
        self._camera = None
        self._tele = None
        if self.camera or self.render_mode is not None:
            self._connect()
        self.scenario: ScenarioSpec | None = None
        self.ego = VehicleState(0.0, EGO_LANE_Y, 0.0, 0.0)
        self.lane_y = EGO_LANE_Y  # the lane the ego starts in; departures are measured from it
        self._hl = self.params.length / 2
        self._hw = self.params.width / 2
        self._car_radius = math.hypot(self._hl, self._hw)

    # ------------------------------------------------------------------ pybullet
    def _connect(self) -> None:
        from .actors import CAR_POOL, PEDESTRIAN_POOL
        from .bodies import BodyPool, c_output_silenced
        from .camera import SegmentationCamera

        with c_output_silenced():  # pybullet's build-time banner
            import pybullet as p

            self._client = p.connect(p.DIRECT)
        vehicle_size = (self.params.length, self.params.width, self.params.height)
        self._pool = BodyPool(self._client, CAR_POOL, PEDESTRIAN_POOL, vehicle_size, PEDESTRIAN_HALF_SIZE)
        self._camera = SegmentationCamera(
            self._client, self._pool, self.image_size, self.fov_deg, self.road_user_cover, self.supersample
        )
        if self.tele_fov_deg is not None:
            self._tele = SegmentationCamera(self._client, self._pool, self.image_size, self.tele_fov_deg)

    def _apply_layout(self) -> None:
        self._pool.apply_layout(self.layout)
        self._camera.set_layout(self.layout)
        if self._tele is not None:
            self._tele.set_layout(self.layout)

    def close(self) -> None:
        if getattr(self, "_client", None) is not None:
            import pybullet as p

            try:
                p.disconnect(physicsClientId=self._client)
            except Exception:  # already gone at interpreter exit
                pass
            self._client = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: pybullet may already be unloaded
            pass

    # ------------------------------------------------------------------ episode
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        spec = (options or {}).get("scenario")
        if spec is None:
            module = families.MODULES.get(self.family)
            spec = module.sample(self.np_random) if module is not None else sample_scenario(self.np_random)
        elif isinstance(spec, dict):
            spec = families.spec_from_dict(spec)
        elif not isinstance(spec, types := families.spec_types()):
            raise TypeError(
                f"options['scenario'] must be a scenario spec ({', '.join(t.__name__ for t in types)}) or its "
                f"dict, not {type(spec).__name__}"
            )
        self.scenario = spec

        rng = np.random.default_rng(spec.seed)
        self.lane_y = float(getattr(spec, "ego_y", EGO_LANE_Y))
        self.ego = VehicleState(0.0, self.lane_y, 0.0, float(spec.ego_speed))
        self.family_state = None
        own_layout = None
        if not isinstance(spec, ScenarioSpec):
            module = families.MODULES[spec.family]
            self.actors, self.family_state = module.build(spec, self._hl, **self.family_options)
            own_layout = getattr(module, "layout", None)
            junction_x = float(rng.uniform(200.0, 300.0))  # the junction well beyond where the episode ends
        else:
            self.actors, junction_x = build_actors(spec, rng, 0.0, self._hl, self.params.length, self.params.width)
        if own_layout is not None:
            self.layout: StaticLayout = own_layout(spec, self.family_state, rng)
        else:
            self.layout = sample_layout(rng, junction_x)
        self._prepare_static()

        self.t_step = 0
        if self.family_state is not None:
            self.horizon_steps = steps_in(self.family_state.horizon_s, self.step_s)
        else:
            self.horizon_steps = horizon_steps(spec.ttc, self.step_s, self.horizon_after_ttc_s, self.max_episode_s)
        self.collisions: list[dict] = []
        self.returns = dict.fromkeys(REGISTRY, 0.0)
        self.ever_departed = False
        self.min_speed = self.ego.v
        self._last_end = None

        if self._pool is not None:
            self._apply_layout()
        return self._observe(), self._info([], dict.fromkeys(REGISTRY, 0.0))

    def _prepare_static(self) -> None:
        rects, circles = self.layout.rects, self.layout.circles
        self._rect_centres = rects[:, :2]
        self._rect_radius = np.hypot(rects[:, 2], rects[:, 3])
        self._circle_centres = circles[:, :2]
        self._circle_radius = circles[:, 2]
        # the narrow phase reads them one number at a time: Python floats, not numpy scalars, whose arithmetic gives
        # the same doubles several times slower
        self._rect_rows, self._circle_rows = rects.tolist(), circles.tolist()
        # centre distance beyond which a body's bounding circle and the ego's cannot meet, with a margin of
        # APART_MARGIN_M so that rounding can never skip a contact the exact test would find; a step's filter
        # (_static_in_reach) reads the distance, each sub-step's test its square
        self._rect_meet = (self._rect_radius + self._car_radius + APART_MARGIN_M).tolist()
        self._rect_apart = [meet * meet for meet in self._rect_meet]
        self._circle_meet = (self._circle_radius + self._car_radius + APART_MARGIN_M).tolist()

    def step(self, action):
        if self.scenario is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be 2 finite numbers [steer, throttle/brake], got {action!r}")
        steer, pedal = float(min(1.0, max(-1.0, a[0]))), float(min(1.0, max(-1.0, a[1])))
        ego, act, dt = self.ego, self.actors, self.step_s
        speed_before = ego.v
        hits, crashed = self._move(steer, pedal)
        self.t_step += 1

        self.collisions.extend(hits)
        state = self.family_state
        family = state.context(act, ego.x + self._hl, ego) if state is not None else {}
        rewards = step_rewards(StepContext(hits, speed_before, ego.v, np.array([steer, pedal]), dt, family, ego.psi))
        for name, value in rewards.items():
            self.returns[name] += value
        self.min_speed = min(self.min_speed, ego.v)
        departed = abs(ego.y - self.lane_y) > LANE_WIDTH / 2
        self.ever_departed |= departed

        left_scene = not (SCENE_X[0] + 10.0 < ego.x < SCENE_X[1] - 20.0) or abs(ego.y) > self.lateral_exit_m
        family_end = state.end(act, ego.x + self._hl, ego.v, family, ego) if state is not None else None
        terminated = crashed or left_scene or family_end is not None
        truncated = not terminated and self.t_step >= self.horizon_steps
        if family_end is not None and not crashed:
            self._last_end = family_end
        elif crashed:
            self._last_end = "crash"
        elif left_scene:
            self._last_end = "left_scene"
        elif truncated:
            self._last_end = "horizon"
        reward = rewards[self.reward_name]
        info = self._info(hits, rewards)
        if terminated or truncated:
            info["outcome"] = self.outcome()
        return self._observe(), reward, terminated, truncated, info

    def _move(self, steer: float, pedal: float) -> tuple[list[dict], bool]:
        """Drive one step in sub-steps, testing the ego's footprint against every road user and static body near
        it at each, up to the first crash: (the collisions, whether the ego crashed)."""
        ego, act, p, dt = self.ego, self.actors, self.params, self.step_s
        sub_dt = dt / self.substeps
        reach = self._car_radius + (ego.v + 3.0) * dt + 1.0
        lo = np.array([ego.x - reach, ego.y - reach])
        hi = np.array([ego.x + reach, ego.y + reach])
        car_idx = geometry.near(act.car_xy, self._car_radius + np.abs(act.car_vel).sum(1) * dt, lo, hi)
        car_idx = [i for i in car_idx if act.car_active[i]]
        ped_idx = geometry.near(act.ped_xy, PEDESTRIAN_RADIUS + np.abs(act.ped_vel).sum(1) * dt, lo, hi)
        ped_idx = [i for i in ped_idx if act.ped_active[i]]
        rect_idx, circ_idx = self._static_in_reach(lo, hi, reach)

        hits: list[dict] = []
        crashed = False
        done_sub = self.substeps
        t0 = self.t_step * dt
        ped_xy, ped_vel, car_xy = act.ped_xy.tolist(), act.ped_vel.tolist(), act.car_xy.tolist()
        car_vel, car_heading = act.car_vel.tolist(), act.car_heading.tolist()
        for k in range(1, self.substeps + 1):
            bumper_before = ego.x + self._hl
            integrate(ego, steer, pedal, sub_dt, p)
            c, s = math.cos(ego.psi), math.sin(ego.psi)
            tau = k * sub_dt
            if self.family_state is not None:  # scripted road users may start moving or turn within the step
                self.family_state.substep(act, bumper_before, ego.x + self._hl, t0, tau, sub_dt)
                ped_idx = range(len(act.ped_active))
                car_idx = np.flatnonzero(act.car_active)
                ped_xy, ped_vel, car_xy = act.ped_xy.tolist(), act.ped_vel.tolist(), act.car_xy.tolist()
                car_vel, car_heading = act.car_vel.tolist(), act.car_heading.tolist()
            for i in ped_idx:
                if not act.ped_active[i]:
                    continue
                px = ped_xy[i][0] + ped_vel[i][0] * tau
                py = ped_xy[i][1] + ped_vel[i][1] * tau
                if geometry.rect_circle(ego.x, ego.y, c, s, self._hl, self._hw, px, py, PEDESTRIAN_RADIUS):
                    act.ped_active[i] = False
                    hits.append(crashes.pedestrian_hit(ego, i, t0 + tau, bool(act.ped_hazard[i])))
            for i in car_idx:
                cx = car_xy[i][0] + car_vel[i][0] * tau
                cy = car_xy[i][1] + car_vel[i][1] * tau
                h = car_heading[i]
                if geometry.rect_rect(
                    ego.x, ego.y, c, s, self._hl, self._hw, cx, cy, math.cos(h), math.sin(h), self._hl, self._hw
                ):
                    point = geometry.closest_point(ego.x, ego.y, cx, cy, math.cos(h), math.sin(h), self._hl, self._hw)
                    hits.append(crashes.vehicle_crash(self, i, t0 + tau, c, s, point))
                    crashed = True
            for i in rect_idx:
                cx, cy, hx, hy, cls = self._rect_rows[i]
                apart = self._rect_apart[i]
                if (cx - ego.x) ** 2 + (cy - ego.y) ** 2 > apart:
                    continue  # the two footprints' bounding circles are apart: the exact test would say no
                if geometry.rect_rect(ego.x, ego.y, c, s, self._hl, self._hw, cx, cy, 1.0, 0.0, hx, hy):
                    point = geometry.closest_point(ego.x, ego.y, cx, cy, 1.0, 0.0, hx, hy)
                    hits.append(crashes.static_crash(self, i, int(cls), t0 + tau, point))
                    crashed = True
            for i in circ_idx:
                cx, cy, r, cls = self._circle_rows[i]
                if geometry.rect_circle(ego.x, ego.y, c, s, self._hl, self._hw, cx, cy, r):
                    hits.append(crashes.static_crash(self, i, int(cls), t0 + tau, (cx, cy)))
                    crashed = True
            if crashed:
                done_sub = k
                break
        act.advance(done_sub * sub_dt)
        return hits, crashed

    def _static_in_reach(self, lo: np.ndarray, hi: np.ndarray, reach: float) -> tuple[list[int], list[int]]:
        """The static rectangles and circles (indices, ascending) that the ego's footprint can touch in a step:
        those near the box [lo, hi] whose bounding circle comes within the ego's while the ego's centre moves at
        most ``reach`` less its radius (the broad phase's 1 m to spare included). The others cannot pass the exact
        tests, so skipping them changes nothing."""
        ex, ey, travel = self.ego.x, self.ego.y, reach - self._car_radius
        rects, circles = self._rect_rows, self._circle_rows
        rect_idx = [
            i
            for i in geometry.near(self._rect_centres, self._rect_radius, lo, hi).tolist()
            if (rects[i][0] - ex) ** 2 + (rects[i][1] - ey) ** 2 <= (self._rect_meet[i] + travel) ** 2
        ]
        circ_idx = [
            i
            for i in geometry.near(self._circle_centres, self._circle_radius, lo, hi).tolist()
            if (circles[i][0] - ex) ** 2 + (circles[i][1] - ey) ** 2 <= (self._circle_meet[i] + travel) ** 2
        ]
        return rect_idx, circ_idx

    # ------------------------------------------------------------------ planning
    def snapshot(self) -> dict:
        """Everything that changes during an episode, copied: ``restore`` on this env or on a camera-less
        ``planning_twin`` continues bit-identically. For privileged planners, which re-simulate from the present."""
        if self.scenario is None:
            raise RuntimeError("call reset() before snapshot()")
        return {
            "scenario": self.scenario,
            "layout": self.layout,
            "horizon_steps": self.horizon_steps,
            "ego": self.ego.copy(),
            "t_step": self.t_step,
            "collisions": list(self.collisions),
            "returns": dict(self.returns),
            "ever_departed": self.ever_departed,
            "min_speed": self.min_speed,
            "last_end": self._last_end,
            "actors": _copy_actors(self.actors),
            "family_state": dataclasses.replace(self.family_state) if self.family_state is not None else None,
        }

    def restore(self, snap: dict) -> None:
        new_layout = getattr(self, "layout", None) is not snap["layout"]
        self.scenario, self.layout, self.horizon_steps = snap["scenario"], snap["layout"], snap["horizon_steps"]
        self.lane_y = float(getattr(self.scenario, "ego_y", EGO_LANE_Y))
        if new_layout:
            self._prepare_static()
            if self._pool is not None:
                self._apply_layout()
        self.actors = _copy_actors(snap["actors"])
        state = snap.get("family_state")
        self.family_state = dataclasses.replace(state) if state is not None else None
        self.ego = snap["ego"].copy()
        self.t_step, self.collisions, self.returns = snap["t_step"], list(snap["collisions"]), dict(snap["returns"])
        self.ever_departed, self.min_speed, self._last_end = snap["ever_departed"], snap["min_speed"], snap["last_end"]

    def planning_twin(self) -> UrbanCollisionEnv:
        """A camera-less env with the same physics, rewards and horizon, to ``restore`` snapshots into."""
        return UrbanCollisionEnv(
            camera=False,
            image_size=self.image_size,
            fov_deg=self.fov_deg,
            tele_fov_deg=self.tele_fov_deg,
            road_user_cover=self.road_user_cover,
            supersample=self.supersample,
            reward=self.reward_name,
            horizon_after_ttc_s=self.horizon_after_ttc_s,
            max_episode_s=self.max_episode_s,
            mu=self.params.mu,
            occupants_per_car=self.occupants_per_car,
            ego_mass=self.ego_mass,
            car_mass=self.car_mass,
            substeps=self.substeps,
            step_s=self.step_s,
            family=self.family,
            family_options=self.family_options,
            lateral_exit_m=self.lateral_exit_m,
        )

    # ------------------------------------------------------------------ collisions
    # ------------------------------------------------------------------ observation / info
    def _observe(self) -> dict:
        size = (self.image_size, self.image_size)
        if self.camera:
            self._sync_bodies()
            seg = self._camera.render(self.ego.x, self.ego.y, self.ego.psi)
        else:
            seg = np.zeros(size, dtype=np.uint8)
        obs = {"seg": seg, "speed": np.array([min(self.ego.v, MAX_SPEED_OBS)], dtype=np.float32)}
        if self.tele_fov_deg is not None:
            e = self.ego
            obs["seg_tele"] = self._tele.render(e.x, e.y, e.psi) if self.camera else np.zeros(size, dtype=np.uint8)
        return obs

    def _sync_bodies(self) -> None:
        a = self.actors
        self._pool.place_actors(a.car_xy, a.car_heading, a.car_active, a.ped_xy, a.ped_active)

    def _info(self, hits: list[dict], rewards: dict[str, float]) -> dict:
        e = self.ego
        return {
            "t": self.t_step * self.step_s,
            "step": self.t_step,
            "collisions": hits,
            **{f"reward_{name}": value for name, value in rewards.items()},
            "x": e.x,
            "y": e.y,
            "heading": e.psi,
            "speed": e.v,
            "steer_angle": e.delta,
            "lane_offset": e.y - self.lane_y,
            "lane_departure": abs(e.y - self.lane_y) > LANE_WIDTH / 2,
            "hazard": self.scenario.hazard,
            "ttc": self.scenario.ttc,
        }

    def outcome(self) -> dict:
        """The paper's section IV-C metrics for the episode so far, as flat scalars."""
        cols = self.collisions
        kinds = {c["kind"] for c in cols}
        first = cols[0]["impact_speed"] if cols else float("nan")
        spec = self.scenario
        extra = self.family_state.outcome(spec, self.ego.x + self._hl) if self.family_state is not None else {}
        return {
            **extra,
            "hazard": spec.hazard,
            "ttc": spec.ttc,
            "ego_speed": spec.ego_speed,
            "pedestrian_collision": int("pedestrian" in kinds),
            "vehicle_collision": int("vehicle" in kinds),
            "static_collision": int("static" in kinds),
            "hazard_collision": int(any(c["hazard"] for c in cols)),
            "n_pedestrians_hit": sum(c["kind"] == "pedestrian" for c in cols),
            "pedestrian_injury": float(sum(c["pedestrian_injury"] for c in cols)),
            "occupant_injury": float(sum(c["occupant_injury"] for c in cols)),
            "ego_occupant_injury": float(sum(c["ego_occupant_injury"] for c in cols)),
            "speed_at_collision": float(first),
            "lane_departure": int(self.ever_departed),
            "min_speed": float(self.min_speed),
            "final_speed": float(self.ego.v),
            "steps": self.t_step,
            **{f"return_{name}": value for name, value in self.returns.items()},
            "end": self._last_end or "running",
        }

    def hazard_pixels(self) -> int:
        """Pixels of the hazard participants in the last rendered frame (0 without a camera)."""
        if self._camera is None:
            return 0
        a = self.actors
        uids = [u for u, hz in zip(self._pool.cars, a.car_hazard) if hz]
        uids += [u for u, hz, on in zip(self._pool.pedestrians, a.ped_hazard, a.ped_active) if hz and on]
        return int(np.isin(self._camera.last_uids, uids).sum()) if uids else 0

    # ------------------------------------------------------------------ rendering for people
    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .camera import colorize

        self._sync_bodies()
        e = self.ego
        seg = self._camera.render(e.x, e.y, e.psi)
        self._pool.place_ego(e.x, e.y, e.psi, visible=True)
        bev_uids = self._camera.birds_eye(e.x, e.y, e.psi, size=128)
        self._pool.place_ego(e.x, e.y, e.psi, visible=False)
        bev = colorize(self._pool.lut[bev_uids + 1])
        bev[bev_uids == self._pool.ego] = (255, 255, 255)  # the ego in white
        scale = 256 // self.image_size
        seg_img = np.kron(colorize(seg), np.ones((scale, scale, 1), dtype=np.uint8)).astype(np.uint8)
        bev_img = np.kron(bev, np.ones((2, 2, 1), dtype=np.uint8)).astype(np.uint8)
        h = max(seg_img.shape[0], bev_img.shape[0])
        canvas = np.zeros((h, seg_img.shape[1] + bev_img.shape[1] + 8, 3), dtype=np.uint8)
        canvas[: seg_img.shape[0], : seg_img.shape[1]] = seg_img
        canvas[: bev_img.shape[0], seg_img.shape[1] + 8 :] = bev_img
        return canvas
