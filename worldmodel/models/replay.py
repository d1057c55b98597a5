"""The circular transition store both learners replay from (``ddpg.ReplayBuffer``, ``dqn.TransitionBuffer``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch


class CircularStore:
    """Fixed-capacity circular store of transitions, one preallocated numpy array per name in ``FIELDS``.

    Once full, each ``add`` overwrites the oldest transition. Subclasses allocate the arrays (shape and dtype per
    field) and give ``add`` its signature. ``terminated`` is 1.0 only for true terminal states; a transition cut by
    a time limit is stored with terminated=0 so that its value is bootstrapped from ``next_obs``.
    """

    FIELDS: tuple[str, ...] = ()
    KIND = "transition buffer"
    RESUME_HINT = "resume with the same buffer size"

    def __init__(self, capacity: int, arrays: dict[str, np.ndarray]):
        self.capacity = int(capacity)
        for name in self.FIELDS:
            setattr(self, name, arrays[name])
        self.pos = 0  # where the next transition goes; once full, also the oldest one
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def advance(self) -> int:
        """The slot the next transition goes to; a subclass's ``add`` writes its fields there (direct array writes:
        ``add`` runs once per environment step)."""
        i = self.pos
        self.pos = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        return i

    def sample(self, n: int, rng: np.random.Generator, replace: bool = True) -> dict[str, torch.Tensor]:
        """``n`` transitions drawn uniformly, with replacement unless ``replace`` is False (then n <= len), as
        tensors keyed by field."""
        if self.size == 0:
            raise ValueError(f"cannot sample from an empty {self.KIND}")
        idx = rng.integers(0, self.size, size=n) if replace else rng.choice(self.size, size=n, replace=False)
        # Fancy indexing copies, so the tensors never alias slots that later adds overwrite.
        return {name: torch.from_numpy(getattr(self, name)[idx]) for name in self.FIELDS}

    def state_dict(self) -> dict[str, Any]:
        # Only the filled part: a checkpoint early in a run stays small. Slots keep their positions, so
        # sampling after a restore draws exactly the transitions it would have drawn before.
        state = {name: getattr(self, name)[: self.size].copy() for name in self.FIELDS}
        state.update(capacity=self.capacity, pos=self.pos, size=self.size)
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if int(state["capacity"]) != self.capacity:
            raise ValueError(
                f"{self.KIND} was saved with capacity {state['capacity']} but this one has {self.capacity}; "
                f"{self.RESUME_HINT}"
            )
        size = int(state["size"])
        for name in self.FIELDS:
            if name in state:  # a field added later (ddpg's n-step `steps`) keeps its default in old checkpoints
                getattr(self, name)[:size] = state[name]
        self.pos, self.size = int(state["pos"]), size
