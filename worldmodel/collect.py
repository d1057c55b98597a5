"""Phase 0: drive the noisy lane-keeping autopilot through paper-distribution scenarios, record to HDF5.

    python -m worldmodel.collect experiment=NAME scale=smoke|quick|paper [resume=true]

Episode i always uses the scenario drawn from ``(seed, i)`` and the autopilot seeded the same way, whatever
the worker count, so two runs with the same config write identical data. With ``collect.branch.share`` > 0, a
share of the episodes also branch: counterfactual continuations under held actions from a snapshot of one of
their states (``worldmodel.recording``, data/README.md). Shards appear only when complete;
after a kill (even SIGKILL) ``resume=true`` writes exactly the missing shards, and the result is identical
to an uninterrupted run.
"""

from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf

from . import artifacts
from .common import resolve_workers
from .config import hydra_main, validate
from .data import SCHEMA_VERSION
from .recording import env_settings, record_dataset


def episode_spec(seed: int, index: int):
    from envs import sample_scenario

    return sample_scenario(np.random.default_rng([seed, index]))


def _collection_settings(cfg) -> dict:
    typed = validate(cfg)
    c = typed.collect
    branch = c.branch.settings()
    return {
        **({"branch": branch} if branch else {}),
        "schema_version": SCHEMA_VERSION,
        "seed": typed.seed,
        "episodes": c.episodes,
        "episodes_per_shard": c.episodes_per_shard,
        "max_episode_s": c.max_episode_s,
        "autopilot": OmegaConf.to_container(cfg.collect.autopilot, resolve=True),
        "env": env_settings(typed),
    }


def autopilot_of(settings: dict, spec):
    from envs import NoisyAutopilot

    ap = settings["autopilot"]
    return NoisyAutopilot(**{**ap, "excursion_s": tuple(ap["excursion_s"])})


def spec_of(settings: dict, index: int):
    return episode_spec(settings["seed"], index)


def run(cfg) -> dict:
    typed = validate(cfg)
    return record_dataset(
        artifacts.rollouts_dir(cfg),
        _collection_settings(cfg),
        spec_of,
        autopilot_of,
        resume=typed.resume,
        num_workers=resolve_workers(typed.collect.num_workers),
        validation_fraction=typed.collect.validation_fraction,
        label="collect",
    )


main = hydra_main("collect")(run)

if __name__ == "__main__":
    main()
