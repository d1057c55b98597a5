"""Behaviour cloning as a learner that fits labelled rows (docs/design.md §5, §11): the actor regressed onto the
planner's actions, in the one training loop (``learners/loop.py``), stopped early on held-out demonstrations.
The paper's DDPG (``learners/ddpg.py``) and Kim et al.'s LIDAR DDPG (``families/kim/teach.py``) clone with it."""

from __future__ import annotations

import numpy as np
import torch

from ..imitation import cloning_fit
from ..models.ddpg import DDPG
from .loop import Curves, HeldOutChecks, fit


def clone(
    agent: DDPG, inputs: np.ndarray, targets: np.ndarray, hp, writer, round_: int, held_out, weights=None
) -> float:
    """Up to ``hp.bc_pretrain_steps`` minibatches of behaviour cloning on (inputs, targets), stopped early: the
    actor kept is the one with the best fit on the held-out demonstrations, checked every 250 minibatches (the
    student overfits a few hundred episodes within a few thousand minibatches). ``weights``: one per sample, on its
    squared error (None: all alike). Curves go to ``writer`` at the minibatch's count over all rounds. Returns the
    last training loss."""
    offset, r = round_ * hp.bc_pretrain_steps, round_
    learner = CloningFit(agent, inputs, targets, hp.ddpg.batch_size, weights, f"bc_loss_round{r}")

    def held_out_fit() -> dict:
        return {f"bc_held_out_round{r}": cloning_fit(agent, held_out)["actor"]}

    checks = HeldOutChecks(
        held_out_fit,
        250,
        hp.bc_pretrain_steps,
        writer,
        "pretrain/",
        offset,
        keep=agent.actor,
        best_of=f"bc_held_out_round{r}",
    )
    fit(learner, hp.bc_pretrain_steps, Curves(writer, "pretrain/", offset=offset), checks)
    if len(held_out):
        checks.restore()
    return learner.loss


class CloningFit:
    """Behaviour cloning as a ``Learner`` of the training loop (learners/loop.py): each update, one minibatch of
    (inputs, targets) drawn with the agent's generator and one step of ``DDPG.clone``; ``weights``: one per sample,
    on its squared error (None: all alike). Its losses are reported under ``name``."""

    def __init__(self, agent: DDPG, inputs: np.ndarray, targets: np.ndarray, batch_size: int, weights, name: str):
        self.agent, self.inputs, self.targets, self.batch_size, self.name = agent, inputs, targets, batch_size, name
        self.weights = None if weights is None else torch.as_tensor(np.asarray(weights, np.float32))
        self.loss, self.steps = float("nan"), 0

    def update(self) -> dict:
        idx = self.agent.rng.integers(0, len(self.inputs), size=self.batch_size)
        w = None if self.weights is None else self.weights[idx]
        self.loss = self.agent.clone(torch.from_numpy(self.inputs[idx]), torch.from_numpy(self.targets[idx]), w)
        self.steps += 1
        return {self.name: self.loss}

    def state_dict(self) -> dict:
        return {"agent": self.agent.state_dict(), "steps": self.steps}  # the agent's holds its cloning optimiser

    def load_state_dict(self, state) -> None:
        self.agent.load_state_dict(state["agent"])
        self.steps = int(state["steps"])
