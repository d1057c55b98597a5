"""How many pixels the hazard pedestrian covers in the first frames, per camera field of view or per view.

    python -m experiments.camera_pixels [--fovs 90,45,30] [--per-cell 10]
    python -m experiments.camera_pixels --views paper64,cover64,pool64   # the 90° camera's views (conf/view/)

The perception bound (docs/results/agent/notes/perception_bound.md), measured at the source. For the validation
bank's pedestrian scenarios at 20 and 30 m/s with TTC <= 1.1 s (seed 4711; the test bank is never touched), the ego
brakes straight and each of its first three frames is rendered at every field of view; the table gives the mean
number of pixels the hazard pedestrian covers (``UrbanCollisionEnv.hazard_pixels``) and the share of scenarios where
it covers none at onset. ~3 s on one core.
"""

from __future__ import annotations

import argparse

import numpy as np

from envs import UrbanCollisionEnv, scenario_bank
from envs.chooser import BRAKE

FRAMES = 3


def pixels(fov: float, entries, **view) -> dict[tuple[float, float], np.ndarray]:
    """(speed, TTC) -> (scenarios, FRAMES) hazard-pedestrian pixels under straight-line braking; ``view``: a view's
    env keywords (``recording.view_env``)."""
    env = UrbanCollisionEnv(fov_deg=fov, **view)
    out: dict[tuple[float, float], list] = {}
    try:
        for e in entries:
            env.reset(options={"scenario": e.spec})
            seen = [env.hazard_pixels()]
            for _ in range(FRAMES - 1):
                env.step(BRAKE)
                seen.append(env.hazard_pixels())
            out.setdefault((e.speed, e.ttc), []).append(seen)
    finally:
        env.close()
    return {k: np.asarray(v) for k, v in out.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fovs", default="90,45,30", help="fields of view, degrees")
    parser.add_argument("--views", default="", help="the 90° camera's views instead of fields of view")
    parser.add_argument("--per-cell", type=int, default=10)
    args = parser.parse_args(argv)
    entries = [
        e
        for e in scenario_bank(per_cell=args.per_cell, seed=4711)
        if e.hazard == "pedestrian" and e.speed >= 20.0 and e.ttc <= 1.1
    ]
    if args.views:
        from worldmodel.recording import view_env

        columns = args.views.split(",")
        counts = {name: pixels(90.0, entries, **view_env(name)) for name in columns}
        head = " | ".join(f"{name}: px frames 0/1/2, none at onset" for name in columns)
    else:
        columns = [float(f) for f in args.fovs.split(",")]
        counts = {fov: pixels(fov, entries) for fov in columns}
        head = " | ".join(f"{fov:g}°: px frames 0/1/2, none at onset" for fov in columns)
    lines = [f"| speed m/s | TTC s | {head} |", "|---:|---:|" + "---:|" * len(columns)]
    for key in sorted(counts[columns[0]]):
        cells = []
        for col in columns:
            a = counts[col][key]
            mean = "/".join(f"{m:.1f}" for m in a.mean(0))
            cells.append(f"{mean}, {100 * (a[:, 0] == 0).mean():.0f} %")
        lines.append(f"| {key[0]:g} | {key[1]:g} | " + " | ".join(cells) + " |")
    print(f"{len(entries)} validation-bank pedestrian scenarios ({args.per_cell} per cell), straight-line braking")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
