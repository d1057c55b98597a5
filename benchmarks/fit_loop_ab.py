"""The fits on labelled rows, timed: the counterfactual actor's critic and actor, and Kim's LIDAR chooser, on fixed
random rows (the fits' own steps are what is timed, not labelling). Run from the checkout to time, e.g. against an
older checkout with ``python -m benchmarks.ab`` (benchmarks/RESULTS.md, "The fits in the training loop")::

    PYTHONPATH=CHECKOUT .venv/bin/python benchmarks/fit_loop_ab.py
"""

from __future__ import annotations

import numpy as np
import torch

from envs.privileged import PRIVILEGED_DIM
from worldmodel import counterfactual
from worldmodel.config import CounterfactualConfig
from worldmodel.families.kim import chooser as kim_chooser
from worldmodel.models.counterfactual import ShiftActor

STATES, PROPOSALS, FEATURES = 4000, 24, 64


def main() -> None:
    torch.set_num_threads(1)
    rows = np.random.default_rng(0)
    x = rows.normal(size=(STATES, FEATURES)).astype(np.float32)
    u = rows.uniform(-1, 1, (STATES, PROPOSALS, 3)).astype(np.float32)
    costs = rows.random((STATES, PROPOSALS)).astype(np.float32)
    state = rows.normal(size=(STATES, PRIVILEGED_DIM)).astype(np.float32)
    held = np.arange(STATES) >= int(0.85 * STATES)
    c = CounterfactualConfig(critic_steps=1500, actor_steps=1500)
    critic, _ = counterfactual.fit_critic(x, u, costs, state, held, c, seed=0, round_=0)
    counterfactual.fit_actor(ShiftActor(FEATURES, (64, 64)), critic, x, x, state, held, c, seed=0, round_=0)
    episodes = 600
    labels = {
        "view": rows.normal(size=(episodes * 5, 40)).astype(np.float32),
        "step": np.tile(np.arange(5), episodes),
        "cost": rows.random((episodes * 5, 5)).astype(np.float32),
        "episode": np.repeat(np.arange(episodes), 5),
    }
    kim_chooser.fit(labels, 5, seed=0, margin=0.0, epochs=20)


if __name__ == "__main__":
    main()
