"""The agent's decision at batch 1: one frame -> [z_t, zhat_{t+1}] (+ speed), and the actor on it.

Two paths compute the same numbers (tests/test_fast_inference.py holds them to float rounding):

* ``ModuleDecision`` / ``ModuleActor``: the trained modules themselves (``SegVAE.encode`` mean, ``WorldRNN.step``
  + ``WorldRNN.predict``, ``torch.tanh(actor.net(x))``). Public torch API only: it works on any torch build.
* ``FastDecision`` / ``FastActor``: the same weights rearranged once for batch 1, about 2x faster (docs/design.md
  §7 asks for <= 1 ms per decision on one thread; ``benchmarks/bench_decision.py``). It leans on torch internals
  that an upgrade may change: oneDNN's private pre-packed linear (``torch.ops.mkldnn._linear_pointwise``,
  ``_reorder_linear_weight``; MKL's ``addmm`` stands in where they are missing), parameter version counters,
  ``as_strided`` im2col and an ``embedding_bag`` lookup.

``decision_path(vae, rnn, use_speed, path="auto")`` picks one; modules on a GPU (``decision_device``) always take
the module path, which runs wherever they are. ``auto`` takes the fast path only after a
self-test: it must build, run, and agree with the module path on a fixed sequence of frames and actions.
Anything else (a missing op, an exception, a mismatch) falls back to the module path with a warning saying
why, so a torch upgrade can slow the agent down but not break it.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as F

from .ddpg import Actor
from .vae import IMAGE_SIZE

log = logging.getLogger(__name__)
PATHS = ("auto", "fast", "module")
ONEDNN_OPS = ("_linear_pointwise", "_reorder_linear_weight")
SELF_TEST_TOL = {"rtol": 1e-4, "atol": 1e-4}


def check_class_map(seg, num_classes: int) -> torch.Tensor:
    """``seg`` as a tensor, if it is an integer ``(64, 64)`` map of ids in ``[0, num_classes)``; else ValueError."""
    seg = torch.as_tensor(seg)
    if seg.shape != (IMAGE_SIZE, IMAGE_SIZE) or seg.is_floating_point() or seg.is_complex() or seg.dtype == torch.bool:
        raise ValueError(
            f"expected an integer class map of shape ({IMAGE_SIZE}, {IMAGE_SIZE}), got {tuple(seg.shape)} {seg.dtype}"
        )
    lo, hi = (int(v) for v in torch.aminmax(seg))
    if lo < 0 or hi >= num_classes:
        raise ValueError(f"class ids must lie in [0, {num_classes}), got range [{lo}, {hi}]")
    return seg


def _conv_rows(weight: torch.Tensor) -> torch.Tensor:
    """Conv weight ``(out, in, kh, kw)`` -> ``(out, kh * kw * in)``, matching a channels-last im2col row."""
    return weight.detach().permute(0, 2, 3, 1).reshape(weight.shape[0], -1).contiguous()


def _onednn_linear_available(ops=ONEDNN_OPS) -> bool:
    """Whether this torch build has oneDNN's pre-packed linear (the op torch.compile uses on x86 CPUs)."""
    try:
        return torch.backends.mkldnn.is_available() and all(hasattr(torch.ops.mkldnn, op) for op in ops)
    except (AttributeError, RuntimeError):
        return False


class _ReluLinear:
    """``relu(x @ weight.T + bias)`` for ``x`` of a fixed number of rows, the weight prepared once.

    oneDNN with the weight pre-packed for that row count (activation fused) beat MKL's ``addmm`` by 35-75 us
    per decision over the three im2col products; MKL is the fallback where oneDNN is missing. oneDNN was slower
    for the single-row products (LSTM +65 us, MDN head +36 us), which therefore stay on ``addmm``.
    """

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor, rows: int, onednn: bool):
        self.bias = bias.detach().clone()
        self.onednn = onednn
        if onednn:
            self.packed = torch.ops.mkldnn._reorder_linear_weight(weight, rows)
        else:
            self.weight_t = weight.t().contiguous()
            self.out = torch.empty(rows, weight.shape[0], dtype=weight.dtype)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.onednn:
            return torch.ops.mkldnn._linear_pointwise(x, self.packed, self.bias, "relu", [], "")
        return torch.addmm(self.bias, x, self.weight_t, out=self.out).relu_()


class FastDecision:
    """One frame -> [z_t, zhat_{t+1}] (+ speed) with the weights of ``vae`` and ``rnn`` rearranged once.

    Measured on 2-core AMD EPYC, one thread (benchmarks/bench_decision.py): the modules' own batch-1 path
    spends its time in the one-hot map and ``_slow_conv2d`` (oneDNN convolutions are slower still: they re-lay
    out the weights on every call), and in module/dispatch overhead. Here:

    * ``enc1``: a convolution over a one-hot map is a sum of weight columns, one per kernel tap. Taps are
      taken in horizontal pixel pairs (13 x 13 = 169 pre-summed columns per pair), so each output pixel
      is one ``embedding_bag`` sum of 8 table rows instead of a 208-long dot product; the bias is folded
      into the first pair's rows.
    * ``enc2..enc4``: channels-last im2col into a preallocated buffer and one matrix product per layer with
      the weight pre-packed (``_ReluLinear``); ``fc_mu``'s columns are permuted to that flatten order.
    * LSTM: one matrix-vector product over ``[z, a, h]`` with the input and recurrent weights side by side
      (pre-transposed: 0.2 ms faster than the transposed view when the weights come from memory), gates
      reordered so the three sigmoids are one call, and the two biases summed.
    * MDN head: only the mixture-weight and mean rows (the log-scales do not enter the point prediction),
      and ``z + sum_k pi_k mu_k`` in one ``addmm`` instead of ``sum_k pi_k (mu_k + z)``.
    * intermediates live in buffers allocated here, and ``logvar`` is never computed.

    The derived weights are a snapshot. Each call checks the version counters of the source parameters
    (bumped by ``load_state_dict``, optimiser steps and any other in-place edit) and rebuilds on a change,
    so the path never runs on stale weights.

    CPU only. ``encode`` returns a view into an internal buffer, overwritten by the next call.
    ``onednn=False`` forces the MKL fallback of ``_ReluLinear`` (default: oneDNN where available).
    """

    path = "fast"

    def __init__(self, vae, rnn, use_speed: bool = False, onednn: bool | None = None):
        if rnn.latent_dim != vae.latent_dim:
            raise ValueError(f"VAE latent size {vae.latent_dim} differs from the LSTM's {rnn.latent_dim}")
        for conv in (vae.enc1, vae.enc2, vae.enc3, vae.enc4):
            if (
                conv.kernel_size != (4, 4)
                or conv.stride != (2, 2)
                or conv.padding != (0, 0)
                or conv.dilation != (1, 1)
                or conv.groups != 1
            ):
                raise ValueError("FastDecision expects SegVAE's encoder (4x4 convolutions, stride 2, no padding)")
        if vae.num_classes > 16:
            raise ValueError(f"FastDecision packs two class ids into a byte: at most 16 classes, got {vae.num_classes}")
        if vae.enc1.weight.device.type != "cpu" or rnn.fc.weight.device.type != "cpu":
            raise ValueError("FastDecision runs on the CPU; move the modules there first")
        self.vae, self.rnn, self.use_speed = vae, rnn, bool(use_speed)
        self.onednn = _onednn_linear_available() if onednn is None else bool(onednn)
        self.C, self.D, self.A, self.H = vae.num_classes, vae.latent_dim, rnn.action_dim, rnn.hidden
        self.K = rnn.gaussians if rnn.head == "mdn" else 0
        self.dim = 2 * self.D + (1 if self.use_speed else 0)
        self.dtype = vae.enc1.weight.dtype
        self._sources = [p for m in (vae.enc1, vae.enc2, vae.enc3, vae.enc4, vae.fc_mu) for p in (m.weight, m.bias)]
        self._sources += [
            rnn.lstm.weight_ih_l0,
            rnn.lstm.weight_hh_l0,
            rnn.lstm.bias_ih_l0,
            rnn.lstm.bias_hh_l0,
            rnn.fc.weight,
            rnn.fc.bias,
        ]
        self._versions: list[int] | None = None
        # Plain tensors even if built under inference_mode: they are updated in place on every call, and a
        # caller may run ``encode`` outside inference_mode.
        with torch.inference_mode(False):
            self._allocate()
        self._build()
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _allocate(self) -> None:
        kw = {"dtype": self.dtype}
        n = IMAGE_SIZE
        sizes = [n]
        for _ in range(4):
            sizes.append((sizes[-1] - 4) // 2 + 1)  # 64 -> 31 -> 14 -> 6 -> 2
        self.sizes = sizes
        s1 = sizes[1]
        self.seg = torch.empty(n, n, dtype=torch.uint8)
        self._seg_np = self.seg.numpy()
        self.pair = torch.empty(n, n // 2, dtype=torch.int32)  # pair (y, x) = pixels (y, 2x) and (y, 2x + 1)
        self.idx = torch.empty(s1 * s1 * 8, dtype=torch.int32)
        self.bag_starts = torch.arange(0, s1 * s1 * 8, 8, dtype=torch.int32)  # given, so embedding_bag makes none
        # Output pixel (i, j) reads rows 2i..2i+3, columns 2j..2j+3, i.e. pairs (2i + r, j + q) for r < 4, q < 2:
        # where each of those 8 pairs sits in `pair`, and which block (r, q) of the table it looks up.
        i, j = torch.arange(s1).view(s1, 1, 1, 1), torch.arange(s1).view(1, s1, 1, 1)
        r, q = torch.arange(4).view(1, 1, 4, 1), torch.arange(2).view(1, 1, 1, 2)
        self.pair_pos = ((2 * i + r) * (n // 2) + (j + q)).reshape(-1)
        self.tap_offset = ((r * 2 + q) * self.C * self.C).expand(s1, s1, 4, 2).reshape(-1).int()
        convs = (self.vae.enc2, self.vae.enc3, self.vae.enc4)
        self.cols = [torch.empty(sizes[k + 2] ** 2, 16 * c.in_channels, **kw) for k, c in enumerate(convs)]
        D, A, H = self.D, self.A, self.H
        self.xh = torch.zeros(1, D + A + H, **kw)  # LSTM input and state side by side: [z_t | a_{t-1} | h]
        self._xh_np = self.xh.numpy()  # writing the action through numpy skips a torch dispatch
        self.c = torch.zeros(1, H, **kw)
        self.gates = torch.empty(1, 4 * H, **kw)
        self.tanh_c = torch.empty(1, H, **kw)
        self.y = torch.empty(1, self.K + self.K * D if self.K else D, **kw)
        self.out = torch.zeros(1, self.dim, **kw)  # [z_t | zhat_{t+1} | speed / 30]

    def _build(self) -> None:
        # refresh() may run inside the caller's inference_mode; the MKL fallback's buffers must stay plain tensors.
        # In this order: inference_mode(False) turns grad mode back on, no_grad then turns it off.
        with torch.inference_mode(False), torch.no_grad():
            self._build_weights()
        self._versions = self._current_versions()

    def _build_weights(self) -> None:
        vae, rnn, C, D = self.vae, self.rnn, self.C, self.D
        taps = vae.enc1.weight.permute(2, 3, 1, 0)  # (ky, kx, class, out)
        taps = taps.reshape(4, 2, 2, C, -1)  # (ky, pair, kx within the pair, class, out)
        pairs = taps[:, :, 0, :, None, :] + taps[:, :, 1, None, :, :]  # (ky, pair, left class, right class, out)
        pairs[0, 0] += vae.enc1.bias
        self.enc1_table = pairs.reshape(8 * C * C, -1).contiguous()
        self.convs = [
            _ReluLinear(_conv_rows(c.weight), c.bias, self.sizes[k + 2] ** 2, self.onednn)
            for k, c in enumerate((vae.enc2, vae.enc3, vae.enc4))
        ]
        # enc4's output rows are (pixel, channel); nn.Flatten of NCHW orders fc_mu's inputs (channel, pixel).
        w = vae.fc_mu.weight.detach()
        self.fc_mu_wt = w.view(D, -1, self.sizes[4] ** 2).transpose(1, 2).reshape(D, -1).t().contiguous()
        self.fc_mu_b = vae.fc_mu.bias.detach().clone()
        lstm, H = rnn.lstm, self.H
        # PyTorch's gate order is (i, f, g, o); (i, f, o, g) puts the three sigmoid gates side by side.
        order = torch.cat([torch.arange(0, 2 * H), torch.arange(3 * H, 4 * H), torch.arange(2 * H, 3 * H)])
        self.lstm_wt = torch.cat([lstm.weight_ih_l0, lstm.weight_hh_l0], dim=1)[order].t().contiguous()
        self.lstm_b = (lstm.bias_ih_l0 + lstm.bias_hh_l0)[order].detach()
        rows = self.y.shape[1]
        self.head_wt = rnn.fc.weight.detach()[:rows].t().contiguous()
        self.head_b = rnn.fc.bias.detach()[:rows].clone()

    def _current_versions(self) -> list[int] | None:
        try:
            return [p._version for p in self._sources]
        except RuntimeError:  # inference tensors (modules built under torch.inference_mode) have no counter
            return None

    def refresh(self) -> None:
        """Re-read the weights if any source parameter changed since the last build."""
        if self._versions is not None and self._versions != self._current_versions():
            self._build()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self.xh.zero_()
        self.c.zero_()

    def note_action(self, action) -> None:
        self._xh_np[0, self.D : self.D + self.A] = np.asarray(action, dtype=np.float32).reshape(self.A)

    @property
    def state(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The LSTM state ``(h, c)``, each ``(1, hidden)`` (views into the working buffers)."""
        return self.xh[:, self.D + self.A :], self.c

    # ------------------------------------------------------------------ running
    def encode(self, seg, speed=None) -> torch.Tensor:
        """``(64, 64)`` class map (numpy or torch) -> ``(1, dim)`` [z_t, zhat_{t+1}(, speed / 30)]."""
        self._load(seg, speed)
        self._encode_mu()
        self._lstm_step()
        self._predict()
        return self.out

    def _load(self, seg, speed) -> None:
        self.refresh()
        if isinstance(seg, np.ndarray) and seg.dtype == np.uint8 and seg.shape == (IMAGE_SIZE, IMAGE_SIZE):
            # the env's own frames: one numpy pass checks them, without torch dispatches
            if seg.max() >= self.C:
                self._bad_ids(int(seg.min()), int(seg.max()))
            self._seg_np[...] = seg
        else:
            self.seg.copy_(self._check_seg(seg))
        if self.use_speed:
            # float32 division, as torch does it on the float32 tensor in the module path
            self.out[0, 2 * self.D] = float(
                np.float32(np.asarray(speed, dtype=np.float32).reshape(-1)[0]) / np.float32(30.0)
            )

    def _check_seg(self, seg) -> torch.Tensor:
        return check_class_map(seg, self.C)

    def _bad_ids(self, lo: int, hi: int):
        # An id >= C would otherwise be read as a valid entry of a neighbouring pair in the enc1 table.
        raise ValueError(f"class ids must lie in [0, {self.C}), got range [{lo}, {hi}]")

    def _encode_mu(self) -> None:
        s1 = self.sizes[1]
        # computed in uint8 (the inputs' type): ids < C <= 16 keep C * left + right below 256
        torch.add(self.seg[:, 1::2], self.seg[:, 0::2], alpha=self.C, out=self.pair)
        torch.index_select(self.pair.view(-1), 0, self.pair_pos, out=self.idx)
        self.idx.add_(self.tap_offset)
        x = F.embedding_bag(self.idx, self.enc1_table, self.bag_starts, mode="sum").relu_().view(s1, s1, -1)
        for k in range(3):
            x = self.convs[k](self._im2col(x, self.cols[k]))
            x = x.view(self.sizes[k + 2], self.sizes[k + 2], -1)
        torch.addmm(self.fc_mu_b, x.view(1, -1), self.fc_mu_wt, out=self.out[:, : self.D])

    @staticmethod
    def _im2col(x: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """Channels-last ``(H, W, C)`` -> rows ``(pixel, ky, kx, C)`` of a 4x4 stride-2 convolution."""
        h, _, c = x.shape
        ho = (h - 4) // 2 + 1
        s0, s1, s2 = x.stride()
        cols.view(ho, ho, 4, 4, c).copy_(x.as_strided((ho, ho, 4, 4, c), (2 * s0, 2 * s1, s0, s1, s2)))
        return cols

    def _lstm_step(self) -> None:
        D, A, H = self.D, self.A, self.H
        xh = self.xh
        xh[:, :D].copy_(self.out[:, :D])
        g = torch.addmm(self.lstm_b, xh, self.lstm_wt, out=self.gates).view(4, H)  # i, f, o, g
        g[:3].sigmoid_()
        g[3].tanh_()
        self.c.mul_(g[1]).addcmul_(g[0], g[3])
        torch.tanh(self.c, out=self.tanh_c)
        torch.mul(g[2:3], self.tanh_c, out=xh[:, D + A :])

    def _predict(self) -> None:
        D, K = self.D, self.K
        z, zhat = self.out[:, :D], self.out[:, D : 2 * D]
        y = torch.addmm(self.head_b, self.xh[:, D + self.A :], self.head_wt, out=self.y)
        if K:
            pi = torch.softmax(y[:, :K], dim=-1)
            if self.rnn.residual:
                torch.addmm(z, pi, y[:, K:].view(K, D), out=zhat)
            else:
                torch.mm(pi, y[:, K:].view(K, D), out=zhat)
        elif self.rnn.residual:
            torch.add(y, z, out=zhat)
        else:
            zhat.copy_(y)


class FastActor:
    """``Actor`` at batch 1 with its own weight tensors (detached views: no copy, always current).

    Same products as ``torch.tanh(actor.net(x))`` (``F.linear`` is ``addmm`` with the transposed weight),
    written into preallocated buffers, without autograd or module-call overhead.
    """

    def __init__(self, actor: Actor):
        layers = list(actor.net)
        linears = layers[0::2]
        if not all(isinstance(m, torch.nn.Linear) for m in linears) or not all(
            isinstance(m, torch.nn.ReLU) for m in layers[1::2]
        ):
            raise ValueError("FastActor expects Actor's Linear-ReLU-...-Linear network")
        w = linears[0].weight
        with torch.inference_mode(False):  # buffers updated in place outside inference_mode, as in FastDecision
            self.layers = [
                (m.weight.detach().t(), m.bias.detach(), torch.empty(1, m.out_features, dtype=w.dtype, device=w.device))
                for m in linears
            ]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """``(1, obs_dim)`` -> ``(1, act_dim)``, a view into an internal buffer."""
        last = len(self.layers) - 1
        for k, (wt, b, out) in enumerate(self.layers):
            x = torch.addmm(b, x, wt, out=out)
            x = x.tanh_() if k == last else x.relu_()
        return x


class ModuleDecision:
    """``FastDecision``'s interface computed by the modules themselves (public torch API only)."""

    path = "module"

    def __init__(self, vae, rnn, use_speed: bool = False):
        if rnn.latent_dim != vae.latent_dim:
            raise ValueError(f"VAE latent size {vae.latent_dim} differs from the LSTM's {rnn.latent_dim}")
        self.vae, self.rnn, self.use_speed = vae, rnn, bool(use_speed)
        self.C, self.D, self.A = vae.num_classes, vae.latent_dim, rnn.action_dim
        self.dim = 2 * self.D + (1 if self.use_speed else 0)
        self.device = next(vae.parameters()).device  # where the modules are: the CPU unless decision_device says
        self.reset()

    def reset(self) -> None:
        self._state = self.rnn.initial_state(1)
        self._action = torch.zeros(1, self.A, device=self.device)
        self.out = torch.zeros(1, self.dim, device=self.device)

    def note_action(self, action) -> None:
        self._action = torch.as_tensor(np.asarray(action, dtype=np.float32).reshape(1, self.A)).to(self.device)

    @property
    def state(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self._state

    @torch.no_grad()
    def encode(self, seg, speed=None) -> torch.Tensor:
        seg = check_class_map(seg, self.C)
        z, _ = self.vae.encode(seg.unsqueeze(0).to(self.device))
        out, self._state = self.rnn.step(z, self._action, self._state)
        parts = [z, self.rnn.predict(out)]
        if self.use_speed:
            parts.append(torch.as_tensor(np.asarray(speed, dtype=np.float32)).reshape(1, 1).to(self.device) / 30.0)
        self.out = torch.cat(parts, dim=1)
        return self.out


class ModuleActor:
    """``FastActor``'s interface on the actor module itself."""

    def __init__(self, actor):
        self.actor = actor
        self.device = next(actor.parameters()).device

    @torch.no_grad()
    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.actor(x.to(self.device))


def _self_test(vae, rnn, use_speed: bool, onednn: bool, steps: int = 4) -> tuple[FastDecision | None, str | None]:
    """Build FastDecision and run it beside ModuleDecision on fixed random frames and actions: ``(fast path, None)``
    if they agree (its state reset), else ``(None, why not)``."""
    rng = np.random.default_rng(0)
    try:
        fast, ref = FastDecision(vae, rnn, use_speed, onednn=onednn), ModuleDecision(vae, rnn, use_speed)
        for _ in range(steps):
            seg = rng.integers(0, vae.num_classes, (IMAGE_SIZE, IMAGE_SIZE), dtype=np.uint8)
            speed = rng.uniform(0, 30, 1).astype(np.float32)
            with torch.inference_mode():
                got = fast.encode(seg, speed).clone()
            want = ref.encode(seg, speed)
            if not torch.allclose(got, want, **SELF_TEST_TOL):
                return None, f"its output differs from the modules' by {float((got - want).abs().max()):.3g}"
            action = rng.uniform(-1, 1, 2).astype(np.float32)
            fast.note_action(action)
            ref.note_action(action)
        fast.reset()
    except Exception as err:  # any failure of torch internals means: use the public path
        return None, f"{type(err).__name__}: {err}"
    return fast, None


def decision_path(vae, rnn, use_speed: bool = False, path: str = "auto", onednn_ops=ONEDNN_OPS):
    """The decision object for ``path``: ``fast``, ``module``, or ``auto`` (fast if it passes its self-test).

    ``onednn_ops`` names the private oneDNN ops the fast path wants; without them it runs on MKL's ``addmm``.
    """
    if path not in PATHS:
        raise ValueError(f"decision path {path!r}: use one of {', '.join(PATHS)}")
    if path == "module" or next(vae.parameters()).device.type != "cpu":  # the fast path is the CPU's
        return ModuleDecision(vae, rnn, use_speed)
    onednn = _onednn_linear_available(onednn_ops)
    if path == "fast":
        return FastDecision(vae, rnn, use_speed, onednn=onednn)
    fast, problem = _self_test(vae, rnn, use_speed, onednn)
    if fast is not None:
        return fast
    log.warning(
        "the fast decision path is unavailable with torch %s (%s); using the module path, which gives "
        "the same numbers more slowly",
        torch.__version__,
        problem,
    )
    return ModuleDecision(vae, rnn, use_speed)


def actor_path(actor, path: str = "auto"):
    """``FastActor`` for the project's ``Actor`` (unless ``path='module'`` or it cannot be built), else the module."""
    if path != "module" and type(actor) is Actor and next(actor.parameters()).device.type == "cpu":
        try:
            return FastActor(actor)
        except Exception as err:
            if path == "fast":
                raise
            log.warning("the fast actor is unavailable (%s: %s); using the module", type(err).__name__, err)
    return ModuleActor(actor)
