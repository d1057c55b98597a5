"""Phase 3a: the privileged planner drives the focus mix with the camera on; recorded for the agent to learn from.

    python -m worldmodel.demonstrate experiment=NAME demos.episodes=N [resume=true]

"Learning by cheating": the planner (``envs/planner.py``) reads the true state and re-simulates its candidate
manoeuvres, but what is recorded is what a camera-only student gets, the frames, speeds and the planner's
actions, in the rollout schema (``data/README.md``) under ``data/NAME/demos/``. ``train_agent`` encodes them
through the frozen world model for behaviour cloning and as demonstrations in DDPG's replay (docs/design.md §5).

Episodes are agent episodes (truncated ``env.horizon_after_ttc_s`` after the TTC) drawn from the focus mix
(``demos.focus``; ``envs.sample_focus_scenario``). Episode i depends only on (seed, i), so the store is identical
whatever ``demos.num_workers``, and a killed run finishes with ``resume=true``.
"""

from __future__ import annotations

import numpy as np

from envs.streams import DEMO_SCENARIOS

from . import artifacts
from .common import StageError, resolve_workers
from .config import hydra_main, teacher_settings, validate
from .data import SCHEMA_VERSION
from .recording import env_settings, record_dataset

MAX_EPISODE_S = 15.0


def demo_settings(cfg) -> dict:
    typed = validate(cfg)
    return {
        "schema_version": SCHEMA_VERSION,
        "source": "planner",
        "seed": typed.seed,
        "episodes": typed.demos.episodes,
        "episodes_per_shard": typed.demos.episodes_per_shard,
        "max_episode_s": MAX_EPISODE_S,
        "horizon_after_ttc_s": typed.env.horizon_after_ttc_s or 3.0,
        "focus": typed.demos.focus.settings(),
        # the planner as evaluated, planning from the first frame, steering to demos.teacher_sides
        "planner": teacher_settings(cfg),
        "env": env_settings(typed),
    }


def spec_of(settings: dict, index: int):
    from envs import sample_focus_scenario

    f = settings["focus"]
    rng = np.random.default_rng([settings["seed"], DEMO_SCENARIOS, index])
    return sample_focus_scenario(rng, f["hazard_share"], tuple(f["speed_range"]), tuple(f["ttc_range"]))


def planner_of(settings: dict, spec):
    from envs.planner import PrivilegedPlanner

    return PrivilegedPlanner.from_settings(**settings["planner"])


def run(cfg) -> dict:
    typed = validate(cfg)
    settings = demo_settings(cfg)
    if settings["episodes"] < 1:
        raise StageError("demos.episodes=0 asks for no demonstrations; pass demos.episodes=N (N >= 1)")
    return record_dataset(
        artifacts.demos_dir(cfg),
        settings,
        spec_of,
        planner_of,
        resume=typed.resume,
        num_workers=resolve_workers(typed.demos.num_workers),
        validation_fraction=0.1,
        label="demonstrate",
    )


main = hydra_main("demonstrate")(run)

if __name__ == "__main__":
    main()
