"""Simulator speed, reset cost, memory over many resets, and hazard visibility at onset.

    python -m benchmarks.bench_env [--resets 10000] [--per-cell 20]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from envs import ScenarioSpec, UrbanCollisionEnv, test_bank
from envs.scenario import sample_scenario

from .common import rss_mb, write


def steps_per_second(camera: bool, steps: int) -> float:
    env = UrbanCollisionEnv(camera=camera, horizon_after_ttc_s=None)
    rng = np.random.default_rng(0)
    env.reset(options={"scenario": sample_scenario(rng)})
    actions = rng.uniform(-0.3, 0.3, size=(steps, 2)).astype(np.float32)
    t0 = time.perf_counter()
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset(options={"scenario": sample_scenario(rng)})
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate


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
    return {"camera": camera, "resets": resets, "reset_ms_p50": 1e3 * float(np.median(times)),
            "reset_ms_p95": 1e3 * float(np.percentile(times, 95)), "rss_before_mb": before, "rss_after_mb": after,
            "rss_growth_mb": after - before}


def visibility(per_cell: int) -> dict:
    """Share of test-bank scenarios whose hazard covers >= 1 pixel of the onset frame, per TTC x speed."""
    env = UrbanCollisionEnv(camera=True)
    cells: dict[str, list[int]] = {}
    for entry in test_bank(per_cell=per_cell):
        env.reset(options={"scenario": entry.spec})
        key = f"{entry.hazard}|{entry.ttc}|{entry.speed:g}"
        cells.setdefault(key, []).append(int(env.hazard_pixels() > 0))
    env.close()
    table = {k: float(np.mean(v)) for k, v in cells.items()}
    overall = float(np.mean([x for v in cells.values() for x in v]))
    return {"fov_deg": env.fov_deg, "per_cell": per_cell, "overall": overall, "cells": table}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--resets", type=int, default=10000)
    ap.add_argument("--per-cell", type=int, default=20)
    args = ap.parse_args(argv)
    result = {
        "steps_per_s_camera_on": steps_per_second(True, args.steps),
        "steps_per_s_camera_off": steps_per_second(False, args.steps * 5),
        "reset_camera_on": reset_cost(True, args.resets),
        "reset_camera_off": reset_cost(False, min(args.resets, 2000)),
        "hazard_visible_at_onset": visibility(args.per_cell),
    }
    print(write("env", result))
    return result


if __name__ == "__main__":
    main()
