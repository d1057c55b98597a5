"""The chooser's networks (docs/design.md §5; fitted by worldmodel/chooser.py): the scorer of every candidate
manoeuvre's cost from the world model's features and the frame band, and the compact inputs it reads."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from envs.chooser import HAZARD_STATE

TARGETS = ("cost", "advantage", "policy")
PREDICT_CHUNK = 512  # rows per forward pass when scoring many labelled states (Scorer.predict): ~0.3 GB of activations


class _MaxPool2x2(torch.autograd.Function):
    """``nn.MaxPool2d(2)``'s values and gradients: the forward pass by the channels-last kernel (~2.4x faster here
    than the NCHW one), the backward pass by the NCHW kernel with those indices (faster than the channels-last one).
    Both kernels pick a window's first largest element, so the indices are the ones ``MaxPool2d`` keeps (tested)."""

    @staticmethod
    def forward(ctx, x):
        y, idx = torch.ops.aten.max_pool2d_with_indices(x.contiguous(memory_format=torch.channels_last), [2, 2], [2, 2])
        idx = idx.contiguous()
        ctx.save_for_backward(x, idx)
        return y.contiguous()

    @staticmethod
    def backward(ctx, grad):
        x, idx = ctx.saved_tensors
        pool_backward = torch.ops.aten.max_pool2d_with_indices_backward
        return pool_backward(grad.contiguous(), x, [2, 2], [2, 2], [0, 0], [1, 1], False, idx)


class MaxPool2x2(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _MaxPool2x2.apply(x) if torch.is_grad_enabled() and x.requires_grad else F.max_pool2d(x, 2)


class Scorer(nn.Module):
    """Features -> predicted cost of every candidate: the mean of ``members`` MLPs, each on features normalised by
    fixed statistics of the training split (buffers, so they travel with the checkpoint).

    ``target``: ``cost`` regresses every candidate's cost. ``advantage`` regresses braking's cost and every other
    candidate's cost *minus* braking's, so the decision (is some candidate cheaper than braking?) is one output's
    sign rather than the difference of two outputs, each with its own error. ``policy`` learns logits whose
    softmax minimises the expected cost relative to braking: the choice itself, with no cost estimated (and so no
    optimistic bias from taking the lowest of several noisy estimates); its "costs" are the negated logits.
    ``mask_shape``: the last features are the frame band of ``MaskView``, read by a small CNN per member."""

    def __init__(
        self,
        in_dim: int,
        n_out: int,
        hidden=(256, 256),
        dropout: float = 0.2,
        members: int = 1,
        target: str = "cost",
        mask_shape: tuple[int, int, int] | None = None,
    ):
        super().__init__()
        self.mask_shape = tuple(mask_shape) if mask_shape else None
        self.mask_dim = int(np.prod(self.mask_shape)) if self.mask_shape else 0
        vec_dim = in_dim - self.mask_dim

        def member():
            layers, d = [], vec_dim
            parts = {}
            if self.mask_shape:  # the frame band through a small CNN, beside the vector features
                ch, h, w = self.mask_shape
                # each pooling before its ReLU: the same values and gradients as after it (max commutes with the
                # ReLU, and both pass a gradient to the window's first largest), on a quarter of the elements
                parts["conv"] = nn.Sequential(
                    nn.Conv2d(ch, 16, 3, padding=1),
                    MaxPool2x2(),
                    nn.ReLU(),
                    nn.Conv2d(16, 32, 3, padding=1),
                    MaxPool2x2(),
                    nn.ReLU(),
                    nn.Flatten(),
                    nn.Linear(32 * (h // 4) * (w // 4), 128),
                    nn.ReLU(),
                )
                d += 128
            for h_ in hidden:
                layers += [nn.Linear(d, int(h_)), nn.ReLU(), nn.Dropout(float(dropout))]
                d = int(h_)
            parts["body"] = nn.Sequential(*layers[:3])  # the first hidden layer, which the auxiliary head reads
            parts["head"] = nn.Sequential(*layers[3:], nn.Linear(d, n_out))
            parts["aux"] = nn.Linear(int(hidden[0]), len(HAZARD_STATE))
            return nn.ModuleDict(parts)

        self.nets = nn.ModuleList(member() for _ in range(int(members)))
        if target not in TARGETS:
            raise ValueError(f"chooser target {target!r}: use one of {TARGETS}")
        self.target = target
        self.register_buffer("mean", torch.zeros(vec_dim))
        self.register_buffer("std", torch.ones(vec_dim))

    def raw(self, x: torch.Tensor, member: int, aux: bool = False):
        """Member ``member``'s outputs (and with ``aux``, its guess of the scaled hazard state)."""
        net = self.nets[member]
        vec = (x[:, : x.shape[1] - self.mask_dim] - self.mean) / self.std
        if self.mask_shape:
            band = x[:, x.shape[1] - self.mask_dim :].reshape(-1, *self.mask_shape)
            vec = torch.cat([vec, net["conv"](band)], dim=1)
        hidden = net["body"](vec)
        out = net["head"](hidden)
        return (out, net["aux"](hidden)) if aux else out

    def to_costs(self, out: torch.Tensor) -> torch.Tensor:
        if self.target == "policy":  # logits: the chooser switches when a logit beats braking's by the margin
            return -out
        return torch.cat([out[:, :1], out[:, :1] + out[:, 1:]], dim=1) if self.target == "advantage" else out

    def loss(self, out: torch.Tensor, costs: torch.Tensor) -> torch.Tensor:
        """Least squares on ``targets(costs)``; for ``policy``, the expected cost over the softmax of the logits
        relative to braking's (cost-sensitive classification: no cost is estimated, the choice is learnt)."""
        if self.target == "policy":
            return (torch.softmax(out, dim=1) * (costs - costs[:, :1])).sum(1).mean()
        return ((out - self.targets(costs)) ** 2).mean()

    def targets(self, costs: torch.Tensor) -> torch.Tensor:
        """What ``raw`` regresses: the costs, or braking's cost and the others' differences from it."""
        return torch.cat([costs[:, :1], costs[:, 1:] - costs[:, :1]], dim=1) if self.target == "advantage" else costs

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([self.to_costs(self.raw(x, m)) for m in range(len(self.nets))]).mean(0)

    @torch.no_grad()
    def predict(self, x: ScorerInputs | np.ndarray | torch.Tensor, chunk: int = PREDICT_CHUNK) -> np.ndarray:
        """The predicted costs of many inputs, ``chunk`` rows at a time: the frame band's convolutions over a whole
        held-out split at once took ~12 GB with 30,000 labelled episodes, and the rows do not interact."""
        x = x if isinstance(x, ScorerInputs) else torch.as_tensor(x)
        rows = (torch.as_tensor(x[i : i + chunk]).to(self.mean.device) for i in range(0, len(x), chunk))
        return torch.cat([self(part).cpu() for part in rows]).numpy()


class ScorerInputs:
    """What the scorer reads for every labelled frame, kept small: the world-model features as float32, and the
    frame band's class masks as uint8 with, per row, the row of the frame before it (-1 at an episode's start).
    ``inputs[rows]`` gives the float rows ``Scorer`` takes, [features, band now, band of the frame before], which
    are exactly ``MaskView``'s; ``subset(rows)`` selects rows without copying. Held as floats, the band took 41 kB
    a labelled frame: 2.5 GB with 15,000 labelled episodes, and as much again while the splits were cut from it."""

    def __init__(self, vec: np.ndarray, current=None, previous=None, index=None):
        self.vec, self.current, self.previous = vec, current, previous
        self.index = np.arange(len(vec)) if index is None else np.asarray(index)
        self.band_dim = 0 if current is None else 2 * int(np.prod(current.shape[1:]))
        self.shape = (len(self.index), vec.shape[1] + self.band_dim)

    def __len__(self) -> int:
        return len(self.index)

    def subset(self, rows) -> ScorerInputs:
        return ScorerInputs(self.vec, self.current, self.previous, self.index[rows])

    def __getitem__(self, rows) -> np.ndarray:
        full = self.index[rows]
        out = np.zeros((len(full), self.shape[1]), np.float32)
        d, half = self.vec.shape[1], self.band_dim // 2
        out[:, :d] = self.vec[full]
        if self.current is not None:
            out[:, d : d + half] = self.current[full].reshape(len(full), -1)
            before = self.previous[full]
            has = before >= 0
            out[has, d + half :] = self.current[before[has]].reshape(int(has.sum()), -1)
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return self[:] if dtype is None else self[:].astype(dtype)
