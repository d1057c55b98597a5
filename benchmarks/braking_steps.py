"""The env's stepping alone, as a whole process to time against another checkout with ``benchmarks/ab.py``:
straight-line braking through a fixed 108-scenario bank, 25 times without the camera or 3 times with it.

    python -m benchmarks.braking_steps off | camera
"""

from __future__ import annotations

import sys

from envs import StraightLineBraking, UrbanCollisionEnv, rollout, scenario_bank


def main(mode: str) -> None:
    bank = scenario_bank(
        ttcs=(0.5, 1.0, 1.5), speeds=(10.0, 20.0, 30.0), hazards=("pedestrian", "car", "both"), per_cell=4, seed=4711
    )
    camera = mode == "camera"
    env = UrbanCollisionEnv(camera=camera)
    for _ in range(3 if camera else 25):
        for entry in bank:
            rollout(env, StraightLineBraking(), entry.spec)
    env.close()


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "off")
