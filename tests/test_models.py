"""Tests of the VAE and the LSTM world model on real modules (no mocks).

Every numeric check compares against an independent computation (hand arithmetic, ``torch.distributions``
or the equivalent torch layer), so a wrong axis, sign or normalisation fails a test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from worldmodel.models.rnn import HEADS, WorldRNN, gaussian_nll, mdn_nll
from worldmodel.models.vae import (
    SegVAE,
    confusion,
    iou_from_confusion,
    kl_per_dim,
    per_class_iou,
    pixel_accuracy,
    vae_loss,
)

torch.set_num_threads(1)  # the machine's 2 cores are shared; one thread keeps timings predictable


# ============================================================================ VAE
def synthetic_maps(n: int = 64, seed: int = 0) -> torch.Tensor:
    """Road-scene-like class maps: sky (10) over road (0) split at a random horizon, plus 1-3 small
    rectangles of car (4), pedestrian (11) or cyclist (12) classes anywhere."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, 64, 64), np.uint8)
    for m in out:
        horizon = rng.integers(8, 57)
        m[:horizon] = 10
        m[horizon:] = 0
        for _ in range(rng.integers(1, 4)):
            hh, ww = rng.integers(4, 11, size=2)
            y0, x0 = rng.integers(0, 64 - hh), rng.integers(0, 64 - ww)
            m[y0 : y0 + hh, x0 : x0 + ww] = rng.choice([4, 11, 12])
    return torch.from_numpy(out)


def test_vae_shapes_and_dtypes():
    torch.manual_seed(0)
    vae = SegVAE()
    seg = torch.randint(0, 13, (3, 64, 64), dtype=torch.uint8)
    mu, logvar = vae.encode(seg)
    assert mu.shape == (3, 128) and logvar.shape == (3, 128)
    # uint8 and int64 inputs are the same map
    mu64, _ = vae.encode(seg.long())
    torch.testing.assert_close(mu, mu64)
    logits = vae.decode(mu)
    assert logits.shape == (3, 13, 64, 64) and logits.dtype == torch.float32
    logits2, mu2, logvar2 = vae(seg, sample=False)
    torch.testing.assert_close(logits2, logits)
    torch.testing.assert_close(logvar2, logvar)
    rec = vae.reconstruct(seg)
    assert rec.shape == (3, 64, 64) and rec.dtype == torch.long
    assert torch.equal(rec, logits.argmax(1))


def test_vae_channels_scale_every_layer_and_keep_the_frame_sizes():
    """channels=c: the encoder's c, 2c, 4c, 8c channels and 32c features, the decoder back; the same 64x64 maps in
    and out, and World Models' sizes at 32."""
    seg = torch.randint(0, 13, (2, 64, 64), dtype=torch.uint8)
    for c in (8, 32):
        vae = SegVAE(latent_dim=16, channels=c)
        convs = [vae.enc1, vae.enc2, vae.enc3, vae.enc4]
        assert [m.out_channels for m in convs] == [c, 2 * c, 4 * c, 8 * c] and vae.fc_mu.in_features == 32 * c
        assert [m.out_channels for m in (vae.dec1, vae.dec2, vae.dec3)] == [4 * c, 2 * c, c]
        logits, mu, _ = vae(seg, sample=False)
        assert logits.shape == (2, 13, 64, 64) and mu.shape == (2, 16)
    assert SegVAE().fc_dec.out_features == 1024 and SegVAE().dec1.out_channels == 128
    with pytest.raises(ValueError, match="channels"):
        SegVAE(channels=0)


def test_vae_one_hot_input_and_bad_ids():
    vae = SegVAE(num_classes=13, latent_dim=8)
    seg = torch.randint(0, 13, (2, 64, 64))
    oh = vae.one_hot(seg)
    assert oh.shape == (2, 13, 64, 64)
    assert torch.equal(oh.argmax(1), seg) and torch.all(oh.sum(1) == 1)
    with pytest.raises(ValueError, match="class ids"):
        vae.encode(torch.full((1, 64, 64), 13))
    with pytest.raises(ValueError, match="shape"):
        vae.encode(torch.zeros(1, 32, 32, dtype=torch.long))


def test_vae_dec1_matmul_equals_transposed_conv():
    """The decoder's first layer is computed as a matmul for speed; it must equal the ConvTranspose2d."""
    torch.manual_seed(0)
    vae = SegVAE()
    h = torch.randn(5, 1024)
    torch.testing.assert_close(vae._dec1_from_vector(h), vae.dec1(h.view(5, 1024, 1, 1)), atol=1e-5, rtol=1e-5)


def test_vae_overfits_small_set():
    """The full VAE (sampled z, summed CE + KL at weight 1) memorises 64 maps.

    The per-pixel mode of the data set is the best accuracy any model can reach without using its input;
    clearing 0.9 well above it proves information flows through the latent and back out spatially.
    """
    maps = synthetic_maps(64, seed=0)
    mode = torch.mode(maps.view(64, -1), dim=0).values.view(1, 64, 64).expand_as(maps)
    baseline = pixel_accuracy(mode, maps)
    assert baseline < 0.82, baseline

    # Measured over torch seeds 0-3: accuracy sits at the baseline for ~100 steps (the decoder first learns
    # the mean map), then crosses 0.9 at step 125-200 (~0.05-0.08 s per step on one shared thread). Seed 2
    # crosses earliest (125), keeping the test ~10 s; the 300-step cap leaves room for numeric drift.
    torch.manual_seed(2)
    vae = SegVAE()
    opt = torch.optim.Adam(vae.parameters(), lr=1e-3, fused=True)
    gen = torch.Generator().manual_seed(2)
    acc, step = 0.0, 0
    for step in range(1, 301):
        batch = maps[torch.randperm(64, generator=gen)[:8]]
        logits, mu, logvar = vae(batch)
        total, recon, kl = vae_loss(logits, batch, mu, logvar)
        assert torch.isfinite(total)
        opt.zero_grad()
        total.backward()
        opt.step()
        if step % 25 == 0:
            acc = pixel_accuracy(vae.reconstruct(maps), maps)
            if acc > 0.9:
                break
    assert acc > 0.9, f"pixel accuracy {acc:.3f} after {step} steps (input-free baseline {baseline:.3f})"


def test_vae_loss_recon_is_summed_ce_averaged_over_batch():
    logits = torch.tensor(
        [
            [[[2.0, 0.0]], [[0.0, 1.0]], [[-1.0, 0.5]]],  # sample 0: 3 classes, 1x2 pixels
            [[[0.0, 0.0]], [[1.0, 0.0]], [[0.0, 3.0]]],  # sample 1
        ]
    )  # (B=2, C=3, H=1, W=2)
    target = torch.tensor([[[0, 2]], [[1, 2]]])

    def ce(scores, k):
        return -(scores[k] - math.log(sum(math.exp(s) for s in scores)))

    hand = (ce([2.0, 0.0, -1.0], 0) + ce([0.0, 1.0, 0.5], 2) + ce([0.0, 1.0, 0.0], 1) + ce([0.0, 0.0, 3.0], 2)) / 2
    mu = torch.zeros(2, 4)
    logvar = torch.zeros(2, 4)
    total, recon, kl = vae_loss(logits, target, mu, logvar)
    assert recon.item() == pytest.approx(hand, rel=1e-6)
    assert kl.item() == 0.0
    assert total.item() == pytest.approx(hand, rel=1e-6)


def test_vae_kl_value_weight_and_free_bits():
    logits = torch.zeros(2, 3, 2, 2)
    target = torch.zeros(2, 2, 2, dtype=torch.long)
    # KL(N(mu, e^lv) || N(0,1)) = 0.5 * (mu^2 + e^lv - 1 - lv) per dim
    mu = torch.tensor([[2.0, 0.0], [0.0, 0.0]])
    logvar = torch.tensor([[0.0, 0.0], [0.0, math.log(2.0)]])
    per = [(0.5 * 4 + 0.0) / 2, (0.0 + 0.5 * (2 - 1 - math.log(2.0))) / 2]  # batch means per dim
    torch.testing.assert_close(kl_per_dim(mu, logvar), torch.tensor(per))
    total, recon, kl = vae_loss(logits, target, mu, logvar, kl_weight=0.25)
    assert kl.item() == pytest.approx(sum(per), rel=1e-6)
    assert total.item() == pytest.approx(recon.item() + 0.25 * sum(per), rel=1e-6)
    # recon of uniform logits: 4 pixels * log 3 per sample
    assert recon.item() == pytest.approx(4 * math.log(3.0), rel=1e-6)

    # free bits: dim 0 (1.0 nat) is above the 0.5 budget and kept, dim 1 (~0.077) is raised to 0.5
    _, _, kl_fb = vae_loss(logits, target, mu, logvar, free_bits=0.5)
    assert kl_fb.item() == pytest.approx(per[0] + 0.5, rel=1e-6)
    # at the prior every dimension is clamped: D * free_bits
    _, _, kl0 = vae_loss(logits, target, torch.zeros(2, 6), torch.zeros(2, 6), free_bits=0.3)
    assert kl0.item() == pytest.approx(6 * 0.3, rel=1e-6)
    # clamped dimensions receive no gradient (that is the point of free bits)
    mu_g = mu.clone().requires_grad_()
    vae_loss(logits, target, mu_g, logvar, free_bits=0.5)[2].backward()
    assert mu_g.grad[:, 1].abs().sum() == 0 and mu_g.grad[0, 0] != 0


def test_confusion_iou_and_accuracy_by_hand():
    pred = np.array([[0, 0, 1], [1, 2, 2]])
    target = np.array([[0, 1, 1], [1, 2, 0]])
    conf = confusion(pred, target, 4)
    expected = np.array([[1, 0, 1, 0], [1, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]])  # rows = true, cols = pred
    assert conf.dtype == np.int64
    np.testing.assert_array_equal(conf, expected)
    # IoU = TP / (pred + true - TP): class 0: 1/(2+2-1), class 1: 2/(2+3-2), class 2: 1/(2+1-1), class 3 absent
    iou = per_class_iou(torch.from_numpy(pred), torch.from_numpy(target), 4)
    np.testing.assert_allclose(iou[:3], [1 / 3, 2 / 3, 1 / 2])
    assert np.isnan(iou[3])
    assert pixel_accuracy(pred, target) == pytest.approx(4 / 6)
    # confusion matrices accumulate over batches
    acc = confusion(pred[:1], target[:1], 4) + confusion(pred[1:], target[1:], 4)
    np.testing.assert_array_equal(acc, conf)
    np.testing.assert_allclose(iou_from_confusion(acc), iou, equal_nan=True)
    # a class predicted but never true has IoU 0, not NaN
    assert iou_from_confusion(np.array([[0, 1], [0, 0]]))[1] == 0.0
    with pytest.raises(ValueError):
        confusion(np.array([4]), np.array([0]), 4)


# ============================================================================ RNN
def test_mdn_nll_single_component_is_gaussian_nll():
    torch.manual_seed(0)
    mu = torch.randn(4, 3, 1, 6)
    logsigma = torch.randn(4, 3, 1, 6) * 0.5
    x = torch.randn(4, 3, 6) * 2
    nll = mdn_nll(torch.zeros(4, 3, 1), mu, logsigma, x)
    assert nll.shape == (4, 3, 6)
    sigma = logsigma.exp()[..., 0, :]
    hand = 0.5 * math.log(2 * math.pi) + logsigma[..., 0, :] + 0.5 * ((x - mu[..., 0, :]) / sigma) ** 2
    torch.testing.assert_close(nll, hand)
    ref = -torch.distributions.Normal(mu[..., 0, :], sigma).log_prob(x)
    torch.testing.assert_close(nll, ref)
    torch.testing.assert_close(gaussian_nll(mu[..., 0, :], logsigma[..., 0, :], x), ref)


def test_mdn_nll_two_components_by_hand():
    logpi = torch.log(torch.tensor([0.3, 0.7]))
    mu = torch.tensor([[0.0, 1.0], [2.0, -1.0]])  # (K=2, D=2)
    logsigma = torch.tensor([[0.0, math.log(0.5)], [math.log(2.0), 0.0]])
    x = torch.tensor([0.5, 0.0])

    def pdf(v, m, s):
        return math.exp(-0.5 * ((v - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))

    hand = [
        -math.log(0.3 * pdf(0.5, 0.0, 1.0) + 0.7 * pdf(0.5, 2.0, 2.0)),
        -math.log(0.3 * pdf(0.0, 1.0, 0.5) + 0.7 * pdf(0.0, -1.0, 1.0)),
    ]
    torch.testing.assert_close(mdn_nll(logpi, mu, logsigma, x), torch.tensor(hand))
    # unnormalised weights are renormalised, not used as-is
    torch.testing.assert_close(mdn_nll(logpi + 3.0, mu, logsigma, x), torch.tensor(hand))


def test_mdn_loss_finite_at_extremes():
    K, D = 3, 4
    logpi = torch.tensor([-1e4, -1e4, 0.0]).expand(2, 5, K).clone().requires_grad_()
    mu = torch.full((2, 5, K, D), 1e4, requires_grad=True)
    for ls in (-50.0, 50.0):
        logsigma = torch.full((2, 5, K, D), ls, requires_grad=True)
        nll = mdn_nll(logpi, mu, logsigma, torch.zeros(2, 5, D))
        assert torch.isfinite(nll).all(), ls
        nll.mean().backward()
        assert all(torch.isfinite(t.grad).all() for t in (logpi, mu, logsigma))
        mu.grad = logpi.grad = None
    # all weights hugely negative and the model's own loss path
    model = WorldRNN(latent_dim=D, action_dim=2, hidden=8, head="mdn", gaussians=K)
    out = {"logpi": torch.full((2, 5, K), -1e4), "mu": -mu.detach(), "logsigma": torch.full((2, 5, K, D), -50.0)}
    assert torch.isfinite(model.loss(out, torch.zeros(2, 5, D)))
    out["logsigma"] = torch.full((2, 5, K, D), 50.0)
    assert torch.isfinite(model.loss(out, torch.zeros(2, 5, D)))


def test_bad_head_is_rejected_by_name():
    with pytest.raises(ValueError, match="'lstm'"):
        WorldRNN(head="lstm")


@pytest.mark.parametrize("head", HEADS)
def test_output_shapes(head):
    torch.manual_seed(0)
    model = WorldRNN(latent_dim=16, action_dim=2, hidden=32, head=head, gaussians=5)
    out, (h, c) = model(torch.randn(3, 7, 16), torch.randn(3, 7, 2))
    assert h.shape == (3, 32) and c.shape == (3, 32)
    if head == "mdn":
        assert out["logpi"].shape == (3, 7, 5)
        assert out["mu"].shape == (3, 7, 5, 16) and out["logsigma"].shape == (3, 7, 5, 16)
        torch.testing.assert_close(out["logpi"].exp().sum(-1), torch.ones(3, 7))
    elif head == "gaussian":
        assert out["mu"].shape == (3, 7, 16) and out["logsigma"].shape == (3, 7, 16)
    else:
        assert set(out) == {"mu"} and out["mu"].shape == (3, 7, 16)
    assert model.predict(out).shape == (3, 7, 16)
    assert model.loss(out, torch.randn(3, 7, 16)).dim() == 0


def _assert_sequence_equals_steps(model, z, a):
    seq_out, seq_state = model(z, a)
    state = model.initial_state(z.shape[0])
    for t in range(z.shape[1]):
        step_out, state = model.step(z[:, t], a[:, t], state)
        for key in seq_out:
            torch.testing.assert_close(step_out[key], seq_out[key][:, t], atol=1e-5, rtol=1e-5)
    for got, want in zip(state, seq_state):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    return seq_out


@pytest.mark.parametrize("head", HEADS)
def test_sequence_equals_stepping_before_and_after_load(head):
    D = 32
    torch.manual_seed(0)
    z, a = torch.randn(3, 10, D), torch.randn(3, 10, 2)
    model = WorldRNN(latent_dim=D, action_dim=2, hidden=64, head=head, gaussians=3)
    _assert_sequence_equals_steps(model, z, a)

    torch.manual_seed(1)
    other = WorldRNN(latent_dim=D, action_dim=2, hidden=64, head=head, gaussians=3)
    ref_out, _ = other(z, a)
    model.load_state_dict(other.state_dict())
    loaded_out = _assert_sequence_equals_steps(model, z, a)
    for key in ref_out:
        torch.testing.assert_close(loaded_out[key], ref_out[key])
    # the step path reads the LSTM's parameters, so it follows in-place updates too (no stale copy)
    with torch.no_grad():
        model.lstm.weight_hh_l0.mul_(1.5)
    _assert_sequence_equals_steps(model, z, a)
    assert not any("cell" in k for k in model.state_dict()), "step must not keep its own weights"


def test_forward_then_step_continues_the_sequence():
    torch.manual_seed(0)
    model = WorldRNN(latent_dim=8, action_dim=2, hidden=16, head="mdn", gaussians=2)
    z, a = torch.randn(2, 6, 8), torch.randn(2, 6, 2)
    full, _ = model(z, a)
    _, state = model(z[:, :4], a[:, :4])
    out, state = model.step(z[:, 4], a[:, 4], state)
    torch.testing.assert_close(out["mu"], full["mu"][:, 4], atol=1e-5, rtol=1e-5)
    out, _ = model(z[:, 5:], a[:, 5:], state)
    torch.testing.assert_close(out["mu"], full["mu"][:, 5:], atol=1e-5, rtol=1e-5)


def test_predict_mixture_mean_by_hand():
    out = {
        "logpi": torch.log(torch.tensor([[0.25, 0.75]])),  # (B=1, K=2)
        "mu": torch.tensor([[[4.0, -2.0, 0.0], [0.0, 2.0, 8.0]]]),  # (1, 2, 3)
        "logsigma": torch.zeros(1, 2, 3),
    }
    zhat = WorldRNN.predict(out)
    torch.testing.assert_close(zhat, torch.tensor([[1.0, 1.0, 6.0]]))
    assert torch.equal(WorldRNN.predict({"mu": out["mu"][:, 0]}), out["mu"][:, 0])


@pytest.mark.parametrize("head", HEADS)
def test_loss_matches_reference_and_mask(head):
    torch.manual_seed(0)
    model = WorldRNN(latent_dim=6, action_dim=2, hidden=16, head=head, gaussians=1)
    out, _ = model(torch.randn(2, 5, 6), torch.randn(2, 5, 2))
    target = torch.randn(2, 5, 6)
    if head == "mse":
        ref = F.mse_loss(out["mu"], target)
    else:
        mu = out["mu"] if head == "gaussian" else out["mu"][..., 0, :]
        ls = out["logsigma"] if head == "gaussian" else out["logsigma"][..., 0, :]
        ref = -torch.distributions.Normal(mu, ls.exp()).log_prob(target).mean()
    torch.testing.assert_close(model.loss(out, target), ref)
    # masking the last two steps equals the loss over the first three
    mask = torch.tensor([[1, 1, 1, 0, 0]] * 2)
    first3 = {k: v[:, :3] for k, v in out.items()}
    torch.testing.assert_close(model.loss(out, target, mask), model.loss(first3, target[:, :3]))


def test_mdn_rnn_learns_simple_dynamics():
    """Gradients through the mixture loss train the LSTM: z_{t+1} = z_t + a_t is learned quickly."""
    torch.manual_seed(0)
    D = 4
    model = WorldRNN(latent_dim=D, action_dim=D, hidden=32, head="mdn", gaussians=3)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)

    def batch():
        z0 = torch.randn(16, 1, D)
        a = torch.randn(16, 9, D) * 0.3
        z = torch.cat([z0, z0 + a.cumsum(1)], dim=1)
        return z[:, :-1], a, z[:, 1:]

    z, a, z_next = batch()
    with torch.no_grad():
        start = F.mse_loss(model.predict(model(z, a)[0]), z_next).item()
    for _ in range(300):
        z, a, z_next = batch()
        loss = model.loss(model(z, a)[0], z_next)
        opt.zero_grad()
        loss.backward()
        opt.step()
    z, a, z_next = batch()
    with torch.no_grad():
        end = F.mse_loss(model.predict(model(z, a)[0]), z_next).item()
    assert end < 0.1 * start, (start, end)


def test_residual_head_starts_at_persistence_and_can_be_turned_off():
    torch.manual_seed(0)
    z = torch.randn(2, 5, 16)
    a = torch.randn(2, 5, 2)
    for head in ("mdn", "gaussian", "mse"):
        rnn = WorldRNN(latent_dim=16, hidden=32, head=head, gaussians=3)
        torch.nn.init.zeros_(rnn.fc.weight)
        torch.nn.init.zeros_(rnn.fc.bias)
        out, _ = rnn(z, a)
        assert torch.allclose(WorldRNN.predict(out), z)  # zero head output = persistence
        plain = WorldRNN(latent_dim=16, hidden=32, head=head, gaussians=3, residual=False)
        plain.load_state_dict(rnn.state_dict())
        out, _ = plain(z, a)
        assert torch.allclose(WorldRNN.predict(out), torch.zeros_like(z))
