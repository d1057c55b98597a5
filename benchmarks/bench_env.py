"""Simulator speed, reset cost, memory over many resets, and hazard visibility at onset.

    python -m benchmarks.bench_env [--resets 10000] [--per-cell 20] [--profile-only]

Steps/s are wall-clock (the docs/design.md §7 target) and also per CPU-second of this process
(``*_cpu``), which other people's jobs on a shared machine disturb much less; ``load_average`` records how busy
the machine was. ``profile_camera_on`` splits a camera-on step into its parts (CPU ms per step).

Profile of the camera (2-core AMD EPYC, shared; wall time, and valgrind instruction counts where other
people's jobs made timings unreliable). Before: 274 steps/s camera on, ~3.2 ms of a ~3.7 ms step inside
``getCameraImage``; actor placement 0.07 ms; dynamics, collisions and the rest ~0.4 ms.

* TinyRenderer draws every body, rasterising each triangle's whole screen bounding box: an empty 64x64 frame
  costs ~0.1 ms (clearing and copying buffers, 1.3 M instructions); each body ~4 us of vertex work even when
  parked far away, behind the camera or below ground; then ~120 instructions per pixel of each triangle's
  bounding box and ~490 per fragment shaded. Posts were already boxes (12 triangles), not cylinders.
* Options do not help: shadows are off by default (shadow=1: +49 %); lightDirection and the light
  coefficients change nothing; ER_NO_SEGMENTATION_MASK saves 1.4 % (and we need the mask); near/far 1/40 m
  instead of 0.1/70 m: -0.3 %. pybullet's numpy output is already on.
* The flat ground (road, two 40 m sidewalks, edge lines, 64 dashes, the side street) was 1.7 ms of a 2.7 ms
  frame: huge, thin triangles whose bounding boxes cover most of the screen. Without it: 1.0 ms.
* A body with alpha 0 is skipped entirely (a parked one is not): hiding the unused pool bodies and the ~85 %
  of the street outside the view frustum took the remaining 1.0 ms to 0.7 ms (~32 bodies drawn per frame).
* Of those 0.7 ms, the ~9 visible buildings were 0.53: their boxes were 24 m tall, buried up to 18 m to vary
  the height, and the buried part was still rasterised. Boxes of 9..24 m buried < 3 m: -12 % of the render's
  instructions.
* Merging scenery does not help: one multibody of 100 box links costs what 100 bodies cost (3.59 M
  instructions per frame either way: TinyRenderer works per visual shape), sub-shapes cannot be moved per
  episode, and createVisualShapeArray with colours segfaults in pybullet 3.2.7.
* ``resetBasePositionAndOrientation`` ~0.7 us and ``changeVisualShape`` ~1.3 us per call; only active actors
  move now, and only bodies whose visibility changes are touched.

After (``envs/camera.py``: the flat ground drawn per pixel from the depth buffer, culling, shorter building
boxes): 813 steps/s wall (819 per CPU-second) with another benchmark running on the second core, ~1,000
steps/s when the machine was quieter. CPU ms per step: getCameraImage 0.66, flat ground 0.14, culling 0.04,
actor placement 0.045, layout placement 0.02, the rest (dynamics, collisions, glue) 0.25.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from envs import UrbanCollisionEnv, scenario_bank
from envs.scenario import sample_scenario

from .common import rss_mb, write


def steps_per_second(
    camera: bool, steps: int, family: str = "porav", tele_fov_deg: float | None = None, seed: int = 0, **view
) -> tuple[float, float]:
    """(wall-clock, CPU-time) steps per second, resets included; ``family="kim"``: Kim's junction (drawn by
    ``camera.CrossroadsGround``), 0.1 s steps, scenarios from its own sampler; ``tele_fov_deg``: with the
    narrow second camera (the chooser_tele agent's), a second render per step; ``view``: a view's env keywords
    (``recording.view_env``)."""
    rng = np.random.default_rng(seed)
    if family == "porav":
        env = UrbanCollisionEnv(camera=camera, horizon_after_ttc_s=None, tele_fov_deg=tele_fov_deg, **view)

        def reset():
            env.reset(options={"scenario": sample_scenario(rng)})
    else:
        env = UrbanCollisionEnv(camera=camera, family=family, step_s=0.1, reward="kim_unaware")

        def reset():
            env.reset(seed=int(rng.integers(2**31)))

    reset()
    actions = rng.uniform(-0.3, 0.3, size=(steps, 2)).astype(np.float32)
    t0, c0 = time.perf_counter(), time.thread_time()
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            reset()
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    env.close()
    return steps / wall, steps / cpu


def profile(steps: int) -> dict:
    """CPU ms per camera-on step by part (each part timed around its call, resets included)."""
    env = UrbanCollisionEnv(camera=True, horizon_after_ttc_s=None)
    cam, pool = env._camera, env._pool
    spent: dict[str, float] = {}

    def timed(obj, name: str, key: str) -> None:
        inner = getattr(obj, name)

        def wrapper(*args, **kwargs):
            t = time.thread_time()
            try:
                return inner(*args, **kwargs)
            finally:
                spent[key] = spent.get(key, 0.0) + time.thread_time() - t

        setattr(obj, name, wrapper)

    timed(cam, "_image", "getCameraImage")
    timed(cam, "_composite_ground", "flat ground (per pixel)")
    timed(cam, "_visible", "culling test")
    timed(pool, "show", "changeVisualShape (show/hide)")
    timed(pool, "place_actors", "actor placement")
    timed(pool, "apply_layout", "layout placement (resets)")
    rng = np.random.default_rng(0)
    env.reset(options={"scenario": sample_scenario(rng)})
    spent.clear()
    actions = rng.uniform(-0.3, 0.3, size=(steps, 2)).astype(np.float32)
    c0 = time.thread_time()
    episodes = 0
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset(options={"scenario": sample_scenario(rng)})
            episodes += 1
    total = time.thread_time() - c0
    env.close()
    out = {k: 1e3 * v / steps for k, v in spent.items()}
    out["rest (dynamics, collisions, env, numpy glue)"] = 1e3 * total / steps - sum(out.values())
    return {
        "steps": steps,
        "resets": episodes,
        "cpu_ms_per_step": 1e3 * total / steps,
        "parts_cpu_ms_per_step": {k: round(v, 4) for k, v in out.items()},
    }


def reset_cost(camera: bool, resets: int) -> dict:
    env = UrbanCollisionEnv(camera=camera)
    rng = np.random.default_rng(1)
    specs = [sample_scenario(rng) for _ in range(min(resets, 500))]
    env.reset(options={"scenario": specs[0]})
    before = rss_mb()
    times = []
    for i in range(resets):
        t0 = time.perf_counter()
        env.reset(options={"scenario": specs[i % len(specs)]})
        times.append(time.perf_counter() - t0)
    after = rss_mb()
    env.close()
    return {
        "camera": camera,
        "resets": resets,
        "reset_ms_p50": 1e3 * float(np.median(times)),
        "reset_ms_p95": 1e3 * float(np.percentile(times, 95)),
        "rss_before_mb": before,
        "rss_after_mb": after,
        "rss_growth_mb": after - before,
    }


def visibility(per_cell: int) -> dict:
    """Share of bank-2018 scenarios whose hazard covers >= 1 pixel of the onset frame, per TTC x speed."""
    env = UrbanCollisionEnv(camera=True)
    cells: dict[str, list[int]] = {}
    for entry in scenario_bank(per_cell=per_cell, seed=2018):
        env.reset(options={"scenario": entry.spec})
        key = f"{entry.hazard}|{entry.ttc}|{entry.speed:g}"
        cells.setdefault(key, []).append(int(env.hazard_pixels() > 0))
    env.close()
    table = {k: float(np.mean(v)) for k, v in cells.items()}
    overall = float(np.mean([x for v in cells.values() for x in v]))
    return {"fov_deg": env.fov_deg, "per_cell": per_cell, "overall": overall, "cells": table}


def views_side_by_side(names: list[str], steps: int, rounds: int = 5) -> dict:
    """Camera-on steps/s of each view (conf/view/), measured in interleaved rounds of ``steps`` steps (view A, B, C,
    A, B, C, ...), each round on its own scenarios, so that a busy spell of the machine falls on every view alike;
    per view the median round, and its ratio to the first view's median. ``NAME@SIZE``: the view at SIZE px."""
    from worldmodel.recording import view_env

    def env_of(name: str) -> dict:
        view, _, size = name.partition("@")  # "paper64@128": the view's keys at another frame size
        return {**view_env(view), **({"image_size": int(size)} if size else {})}

    kwargs = {name: env_of(name) for name in names}
    walls: dict[str, list[float]] = {name: [] for name in names}
    cpus: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        for name in names:
            wall, cpu = steps_per_second(True, steps, seed=r, **kwargs[name])
            walls[name].append(wall)
            cpus[name].append(cpu)
    base = float(np.median(cpus[names[0]]))
    return {
        name: {
            "env": kwargs[name],
            "steps_per_s": float(np.median(walls[name])),
            "steps_per_s_cpu": float(np.median(cpus[name])),
            "cpu_ratio_to_" + names[0]: float(np.median(cpus[name])) / base,
            "rounds": rounds,
            "steps_per_round": steps,
        }
        for name in names
    }


def band_render_ms(frames: int = 300) -> dict:
    """CPU ms of one TinyRenderer frame: the 64×64 frame, and horizon bands of the same 90° width at 4× the pixels per
    degree (256 px wide; rows 22-34 and 20-44 of the 64-px frame, 48 and 96 px tall, by an off-axis frustum), with the
    same bodies drawn. A band view's render alone, before anything reads it."""
    import pybullet as p

    env = UrbanCollisionEnv(camera=True, horizon_after_ttc_s=None)
    env.reset(options={"scenario": sample_scenario(np.random.default_rng(0))})
    cam, ego = env._camera, env.ego
    cam.pool.show(cam._visible(ego.x, ego.y, ego.psi))
    view, n = cam._view(ego.x, ego.y, ego.psi), cam.near
    shapes = {"frame 64x64": (64, 64, cam.projection)}
    for r0, r1 in ((22, 34), (20, 44)):
        top, bottom = (1 - 2 * r0 / 64) * n, (1 - 2 * r1 / 64) * n
        proj = p.computeProjectionMatrix(-n, n, bottom, top, n, cam.far, physicsClientId=cam.client)
        shapes[f"band 256x{4 * (r1 - r0)} (rows {r0}-{r1})"] = (256, 4 * (r1 - r0), proj)
    out = {}
    for name, (w, h, proj) in shapes.items():
        t0 = time.thread_time()
        for _ in range(frames):
            p.getCameraImage(w, h, view, proj, renderer=p.ER_TINY_RENDERER, physicsClientId=cam.client)
        out[name] = 1e3 * (time.thread_time() - t0) / frames
    env.close()
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--views",
        default="",
        help="only the views' steps/s side by side, e.g. paper64,cover64,pool64; NAME@SIZE renders a view at SIZE px "
        "(the env only: no world model takes other sizes)",
    )
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--resets", type=int, default=10000)
    ap.add_argument("--per-cell", type=int, default=20)
    ap.add_argument("--profile-only", action="store_true", help="print the per-part profile; write nothing")
    args = ap.parse_args(argv)
    if args.views:
        given = " ".join(argv if argv is not None else sys.argv[1:])
        result = {"command": f"python -m benchmarks.bench_env {given}", "loadavg_at_start": list(os.getloadavg())}
        result["views"] = views_side_by_side(args.views.split(","), max(args.steps // 5, 100))
        result["render_cpu_ms"] = band_render_ms()
        print(write("env_views", result))
        return result
    if args.profile_only:
        result = profile(args.steps)
        print(json.dumps(result, indent=2))
        return result
    load_before = os.getloadavg()
    on_wall, on_cpu = steps_per_second(True, args.steps)
    off_wall, off_cpu = steps_per_second(False, args.steps * 5)
    kim_wall, kim_cpu = steps_per_second(True, args.steps, family="kim")
    tele_wall, tele_cpu = steps_per_second(True, args.steps, tele_fov_deg=30.0)
    result = {
        "steps_per_s_camera_on_tele": tele_wall,
        "steps_per_s_camera_on_tele_cpu": tele_cpu,
        "steps_per_s_camera_on_kim": kim_wall,
        "steps_per_s_camera_on_kim_cpu": kim_cpu,
        "steps_per_s_camera_on": on_wall,
        "steps_per_s_camera_off": off_wall,
        "steps_per_s_camera_on_cpu": on_cpu,
        "steps_per_s_camera_off_cpu": off_cpu,
        "load_average": {"before": list(load_before), "after_steps": list(os.getloadavg())},
        "profile_camera_on": profile(args.steps),
        "reset_camera_on": reset_cost(True, args.resets),
        "reset_camera_off": reset_cost(False, min(args.resets, 2000)),
        "hazard_visible_at_onset": visibility(args.per_cell),
    }
    print(write("env", result))
    return result


if __name__ == "__main__":
    main()
