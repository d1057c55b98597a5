"""The counterfactual-cost actor's networks (docs/design.md §5; trained by worldmodel/counterfactual.py): the
ensemble critic of a shift's R2 cost, the actor that proposes the shift, and the state features both read."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from envs.privileged import PRIVILEGED_DIM

from .ddpg import Actor, mlp


class Normalised(nn.Module):
    """Fixed per-feature statistics of the training states (buffers, so they travel with the checkpoint)."""

    def __init__(self, in_dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(in_dim))
        self.register_buffer("std", torch.ones(in_dim))

    def fit(self, x: torch.Tensor) -> None:
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-2))  # a feature constant in training stays 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class CostCritic(nn.Module):
    """(state features, u) -> every member's predicted R2 cost, shape (members, batch). Each member reads the state
    through a first layer of its own, and u joins after it; a linear head on that layer guesses the true state
    (``envs.privileged``), a training target only (``aux``)."""

    def __init__(self, in_dim: int, members: int, hidden, aux_dim: int = PRIVILEGED_DIM, u_dim: int = 3):
        """``u_dim``: the width of what joins after the first layer: a shift's 3 parameters, or a fixed set's codes
        (``train_rounds``' ``choices``)."""
        super().__init__()
        hidden = [int(h) for h in hidden]
        self.norm = Normalised(in_dim)
        self.trunks = nn.ModuleList(nn.Sequential(nn.Linear(in_dim, hidden[0]), nn.ReLU()) for _ in range(members))
        self.heads = nn.ModuleList(mlp(hidden[0] + int(u_dim), hidden[1:], 1) for _ in range(int(members)))
        self.aux = nn.ModuleList(nn.Linear(hidden[0], aux_dim) for _ in range(int(members)))

    def member(self, m: int, x: torch.Tensor, u: torch.Tensor, aux: bool = False):
        h = self.trunks[m](self.norm(x))
        out = self.heads[m](torch.cat([h, u], dim=1))[:, 0]
        return (out, self.aux[m](h)) if aux else out

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return torch.stack([self.member(m, x, u) for m in range(len(self.heads))])

    def grid(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Every member's cost of each state's ``k`` shifts ``u`` (batch, k, 3): (members, batch, k). Each state's
        first layer is computed once, not once per shift."""
        x = self.norm(x)
        out = []
        for trunk, head in zip(self.trunks, self.heads, strict=True):
            h = trunk(x)[:, None].expand(-1, u.shape[1], -1)
            out.append(head(torch.cat([h, u], dim=2))[..., 0])
        return torch.stack(out)


class ShiftActor(nn.Module):
    """The paper's actor network (``models.ddpg.Actor``) on the normalised state features: u in [-1, 1]^3, braking
    at initialisation. A linear head on its first hidden layer guesses the true state (``aux``; training only)."""

    def __init__(self, in_dim: int, hidden, aux_dim: int = PRIVILEGED_DIM):
        super().__init__()
        self.norm = Normalised(in_dim)
        self.actor = Actor(in_dim, 3, tuple(int(h) for h in hidden), final_bound=0.0)
        self.aux = nn.Linear(int(hidden[0]), aux_dim)

    def forward(self, x: torch.Tensor, aux: bool = False):
        net = self.actor.net
        h = net[1](net[0](self.norm(x)))
        u = torch.tanh(net[2:](h))
        return (u, self.aux(h)) if aux else u


def features(encoded: np.ndarray, d: np.ndarray, decisions: int) -> np.ndarray:
    """The learner's state: the world model's view, then the decision's index as a share of the decisions."""
    return np.concatenate([encoded, (np.asarray(d, np.float32) / decisions)[:, None]], axis=1).astype(np.float32)


def actor_from_state(state: dict) -> ShiftActor:
    actor = ShiftActor(int(state["in_dim"]), state["actor_hidden"])
    actor.load_state_dict(state["actor"])
    return actor.eval()
