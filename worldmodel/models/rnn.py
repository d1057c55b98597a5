"""The world model's memory: an LSTM over ``[z_t, a_t]`` that predicts the next latent ``z_{t+1}``.

Follows the World Models MDN-RNN (Ha & Schmidhuber 2018): a 512-unit LSTM whose output head parameterises
``p(z_{t+1} | z_<=t, a_<=t)``. Three heads are available so the choice can be ablated:

* ``"mdn"``: a mixture of ``K`` diagonal Gaussians. ONE set of ``K`` mixture weights is shared by all latent
  dimensions (``logpi`` is ``(B, T, K)``), while each component has its own per-dimension mean and scale.
  World Models gives every dimension its own weights; sharing them keeps the head small (``K + 2KD``
  outputs instead of ``3KD``) and lets a component stand for a whole-scene outcome (e.g. "the pedestrian
  steps out" vs "stays"). The loss is still World Models' per-dimension NLL (see :func:`mdn_nll`), which
  scores each dimension's marginal mixture rather than the joint likelihood of one shared component choice.
* ``"gaussian"``: a single diagonal Gaussian (the ``K = 1`` special case, without the softmax).
* ``"mse"``: a deterministic point prediction trained with mean squared error.

Training uses :meth:`WorldRNN.forward` over whole sequences (cuDNN/oneDNN-fused ``nn.LSTM``); the agent
uses :meth:`WorldRNN.step` one frame at a time. ``step`` computes the LSTM cell directly from the
``nn.LSTM``'s own parameter tensors, so there is exactly one copy of the weights and the two paths cannot
drift apart after training or ``load_state_dict``. The agent's per-frame decision runs the same step through
``worldmodel.models.fast_decision.FastDecision`` (both weight matrices side by side in one product, rebuilt
whenever these parameters change), which tests/test_fast_inference.py holds equal to ``step`` + ``predict``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["WorldRNN", "mdn_nll", "gaussian_nll", "HEADS", "LOGSIGMA_MIN", "LOGSIGMA_MAX"]

HEADS = ("mdn", "gaussian", "mse")
# Scales outside e^-7 .. e^5 are never useful for a unit-prior latent and only produce overflow
# (exp(-logsigma) squared) or vanishing gradients; clamping here makes the loss finite for any input.
LOGSIGMA_MIN = -7.0
LOGSIGMA_MAX = 5.0
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)

State = tuple[torch.Tensor, torch.Tensor]


def gaussian_nll(mu: torch.Tensor, logsigma: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-element ``-log N(target; mu, exp(logsigma)^2)``, with ``logsigma`` clamped to a sane range."""
    logsigma = logsigma.clamp(LOGSIGMA_MIN, LOGSIGMA_MAX)
    zscore = (target - mu) * torch.exp(-logsigma)
    return _HALF_LOG_2PI + logsigma + 0.5 * zscore.pow(2)


def mdn_nll(logpi: torch.Tensor, mu: torch.Tensor, logsigma: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-element negative log-likelihood under a mixture with weights shared across dimensions.

    Shapes: ``logpi (..., K)``, ``mu`` and ``logsigma (..., K, D)``, ``target (..., D)``; returns ``(..., D)``
    with ``nll[..., d] = -log sum_k pi_k N(target_d; mu_kd, sigma_kd)``, i.e. each dimension's marginal
    likelihood, as World Models trains its MDN (averaging these over dimensions gives its loss).

    ``logpi`` may be unnormalised logits: it is passed through ``log_softmax`` (a no-op on already normalised
    log-weights), so a caller cannot silently train with weights that do not sum to one. The mixture sum is a
    ``logsumexp``, and ``logsigma`` is clamped, so extreme inputs give large but finite values.
    """
    if mu.shape != logsigma.shape or mu.shape[:-1] != logpi.shape or mu.shape[:-2] + mu.shape[-1:] != target.shape:
        raise ValueError(
            "mdn_nll expects logpi (..., K), mu/logsigma (..., K, D), target (..., D); got "
            f"{tuple(logpi.shape)}, {tuple(mu.shape)}, {tuple(logsigma.shape)}, {tuple(target.shape)}"
        )
    logpi = F.log_softmax(logpi, dim=-1)
    comp_ll = -gaussian_nll(mu, logsigma, target.unsqueeze(-2))  # (..., K, D)
    return -torch.logsumexp(logpi.unsqueeze(-1) + comp_ll, dim=-2)


class WorldRNN(nn.Module):
    """LSTM world model ``(z_t, a_t, h_t) -> p(z_{t+1})``.

    The recurrent state is ``(h, c)``, each ``(B, hidden)``, for both :meth:`forward` and :meth:`step`, so a
    context can be consumed with ``forward`` and continued with ``step`` (or vice versa).
    """

    def __init__(
        self,
        latent_dim: int = 128,
        action_dim: int = 2,
        hidden: int = 512,
        head: str = "mdn",
        gaussians: int = 5,
        residual: bool = True,
    ):
        super().__init__()
        if head not in HEADS:
            raise ValueError(f"unknown WorldRNN head {head!r}; expected one of {', '.join(HEADS)}")
        if head == "mdn" and gaussians < 1:
            raise ValueError(f"gaussians must be >= 1 for the mdn head, got {gaussians}")
        self.latent_dim = int(latent_dim)
        self.action_dim = int(action_dim)
        self.hidden = int(hidden)
        self.head = head
        self.gaussians = int(gaussians) if head == "mdn" else 1
        # Residual: the head predicts z_{t+1} - z_t, so an untrained model is the persistence baseline and
        # training only has to learn motion. Without it, a short run predicted worse than persistence
        # (quick scale: vehicles IoU 0.52 vs 0.59).
        self.residual = bool(residual)

        self.lstm = nn.LSTM(latent_dim + action_dim, hidden, batch_first=True)
        D, K = self.latent_dim, self.gaussians
        out_dim = {"mdn": K + 2 * K * D, "gaussian": 2 * D, "mse": D}[head]
        self.fc = nn.Linear(hidden, out_dim)

    # ------------------------------------------------------------------ plumbing
    def initial_state(self, batch: int) -> State:
        """Zero ``(h, c)``, each ``(batch, hidden)``, on the module's device and dtype."""
        w = self.lstm.weight_hh_l0
        zeros = torch.zeros(batch, self.hidden, device=w.device, dtype=w.dtype)
        return zeros, zeros.clone()

    def _inputs(self, z: torch.Tensor, a: torch.Tensor, ndim: int) -> torch.Tensor:
        if z.dim() != ndim or a.dim() != ndim or z.shape[:-1] != a.shape[:-1]:
            lead = "(B, T, ·)" if ndim == 3 else "(B, ·)"
            raise ValueError(
                f"z and a must both be {lead} with matching leading dims; got {tuple(z.shape)}, {tuple(a.shape)}"
            )
        if z.shape[-1] != self.latent_dim or a.shape[-1] != self.action_dim:
            raise ValueError(
                f"expected latent size {self.latent_dim} and action size {self.action_dim}; "
                f"got {z.shape[-1]} and {a.shape[-1]}"
            )
        return torch.cat([z, a.to(z.dtype)], dim=-1)

    def _head(self, h: torch.Tensor, z: torch.Tensor) -> dict[str, torch.Tensor]:
        """Map LSTM outputs ``(..., hidden)`` (and the input ``z_t``) to the parameters of ``z_{t+1}``."""
        y = self.fc(h)
        lead, D, K = y.shape[:-1], self.latent_dim, self.gaussians
        base = z if self.residual else torch.zeros_like(z)
        if self.head == "mse":
            return {"mu": y + base}
        if self.head == "gaussian":
            mu, logsigma = y.split([D, D], dim=-1)
            return {"mu": mu + base, "logsigma": logsigma.clamp(LOGSIGMA_MIN, LOGSIGMA_MAX)}
        logits, mu, logsigma = y.split([K, K * D, K * D], dim=-1)
        return {
            "logpi": F.log_softmax(logits, dim=-1),
            "mu": mu.reshape(*lead, K, D) + base.unsqueeze(-2),
            "logsigma": logsigma.reshape(*lead, K, D).clamp(LOGSIGMA_MIN, LOGSIGMA_MAX),
        }

    # ------------------------------------------------------------------ running
    def forward(
        self, z: torch.Tensor, a: torch.Tensor, state: State | None = None
    ) -> tuple[dict[str, torch.Tensor], State]:
        """Run whole sequences: ``z (B, T, D)``, ``a (B, T, A)`` -> ``(out, (h, c))``.

        ``out[...][:, t]`` is the prediction of ``z[:, t + 1]``. ``state`` defaults to zeros.
        """
        x = self._inputs(z, a, ndim=3)
        if state is None:
            state = self.initial_state(x.shape[0])
        h0, c0 = state
        y, (h, c) = self.lstm(x, (h0.unsqueeze(0).contiguous(), c0.unsqueeze(0).contiguous()))
        return self._head(y, z), (h.squeeze(0), c.squeeze(0))

    def step(
        self, z: torch.Tensor, a: torch.Tensor, state: State | None = None
    ) -> tuple[dict[str, torch.Tensor], State]:
        """Advance one frame: ``z (B, D)``, ``a (B, A)`` -> ``(out, (h, c))`` with ``out`` shapes minus ``T``.

        The gates are computed from ``self.lstm``'s own ``weight_ih_l0``/``weight_hh_l0``/biases with PyTorch's
        gate order (input, forget, cell, output), so no separate cell (and no weight copy) exists.
        """
        x = self._inputs(z, a, ndim=2)
        h, c = self.initial_state(x.shape[0]) if state is None else state
        lstm = self.lstm
        gates = F.linear(x, lstm.weight_ih_l0, lstm.bias_ih_l0) + F.linear(h, lstm.weight_hh_l0, lstm.bias_hh_l0)
        i, f, g, o = gates.chunk(4, dim=-1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        return self._head(h, z), (h, c)

    # ------------------------------------------------------------------ training / use
    def loss(
        self, out: dict[str, torch.Tensor], z_next: torch.Tensor, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Scalar loss of predicting ``z_next`` (same leading shape as ``out``), averaged over every element.

        mdn: mixture NLL per dimension (:func:`mdn_nll`); gaussian: Gaussian NLL per dimension; mse: squared
        error. All are means over batch, time and latent dims, so values are comparable across latent sizes.
        ``mask`` (leading shape, e.g. ``(B, T)``; 1 = real step) excludes padded steps after an episode ends.
        """
        if self.head == "mdn":
            per = mdn_nll(out["logpi"], out["mu"], out["logsigma"], z_next)
        elif self.head == "gaussian":
            per = gaussian_nll(out["mu"], out["logsigma"], z_next)
        else:
            if out["mu"].shape != z_next.shape:
                raise ValueError(f"prediction {tuple(out['mu'].shape)} and target {tuple(z_next.shape)} differ")
            per = (out["mu"] - z_next).pow(2)
        if mask is None:
            return per.mean()
        if mask.shape != per.shape[:-1]:
            raise ValueError(
                f"mask shape {tuple(mask.shape)} must equal the target's leading shape {tuple(per.shape[:-1])}"
            )
        weight = mask.to(per.dtype).unsqueeze(-1)
        return (per * weight).sum() / (weight.sum() * per.shape[-1]).clamp(min=1.0)

    @staticmethod
    def predict(out: dict[str, torch.Tensor]) -> torch.Tensor:
        """Point prediction of ``z_{t+1}``: the mixture mean ``sum_k pi_k mu_k`` for mdn, else ``mu``."""
        if "logpi" in out:
            pi = out["logpi"].softmax(dim=-1)
            return (pi.unsqueeze(-1) * out["mu"]).sum(dim=-2)
        return out["mu"]
