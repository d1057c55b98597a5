"""Phase 2 on real smoke-scale data: encoding cache, provenance of the VAE, resume, validation, errors."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch

from worldmodel import artifacts, loading, train_rnn, train_vae
from worldmodel.common import StageError
from worldmodel.latents import Latents

# What the stage measures after training (next-frame IoU aside: the dreams, the action effect) is tested in
# tests/test_dreams.py; these tests check the training and its inputs, and skip it (0 skips a measurement).
NO_DREAMS = ("rnn.effect_points=0", "rnn.horizon_episodes=0")


@pytest.fixture
def with_vae(experiment_copy):
    return experiment_copy("vae")


def retrain_vae(stage_cfg, root) -> str:
    """Replace the experiment's VAE by one trained from another seed (so its checkpoint surely differs)."""
    before = artifacts.vae_id(stage_cfg("train_vae"))
    artifacts.retire(stage_cfg("train_vae"), root / "runs/t/vae")
    train_vae.run(stage_cfg("train_vae", "seed=1"))
    after = artifacts.vae_id(stage_cfg("train_vae"))
    assert after != before
    return after


def test_missing_vae_names_the_command(stage_cfg):
    with pytest.raises(StageError, match="worldmodel.train_vae experiment=t"):
        train_rnn.run(stage_cfg("train_rnn"))


def test_reencodes_only_when_the_vae_checkpoint_changes(stage_cfg, with_vae):
    first = train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS))
    assert first["reencoded_latents"] is True
    latents = with_vae / "data/t/latents.h5"
    stamp = latents.stat().st_mtime_ns

    # Same VAE: the encoding is reused.
    second = train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS, "rnn.epochs=2", "resume=true"))
    assert second["reencoded_latents"] is False and latents.stat().st_mtime_ns == stamp

    # Another VAE: resuming the LSTM run started on the old one is refused, naming what changed ...
    new_vae = retrain_vae(stage_cfg, with_vae)
    with pytest.raises(StageError, match=r"vae .* -> " + artifacts.short(new_vae)):
        train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS, "rnn.epochs=3", "resume=true"))
    # ... and a fresh LSTM run encodes the dataset again with the new VAE.
    artifacts.retire(stage_cfg("train_rnn", *NO_DREAMS), with_vae / "runs/t/rnn")
    third = train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS))
    assert third["reencoded_latents"] is True and latents.stat().st_mtime_ns != stamp
    lat = Latents(latents)
    assert lat.f.attrs["vae_sha256"] == new_vae
    lat.close()
    record = json.loads((with_vae / "runs/t/rnn/provenance.json").read_text())
    assert record["inputs"]["vae"] == new_vae


def test_lstm_trained_on_another_vae_refuses_to_load(stage_cfg, with_vae, caplog):
    train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS))
    old_vae = artifacts.vae_id(stage_cfg("train_rnn", *NO_DREAMS))
    new_vae = retrain_vae(stage_cfg, with_vae)
    with pytest.raises(StageError) as err:
        loading.load_rnn(stage_cfg("train_rnn", *NO_DREAMS))
    message = str(err.value)
    for part in (
        str(with_vae / "runs/t/rnn/best.pt"),
        str(with_vae / "runs/t/vae/best.pt"),
        artifacts.short(old_vae),
        artifacts.short(new_vae),
        "python -m worldmodel.train_rnn experiment=t",
        "allow_stale=true",
    ):
        assert part in message, (part, message)
    with caplog.at_level(logging.WARNING):
        rnn, _ = loading.load_rnn(stage_cfg("train_rnn", *NO_DREAMS, "allow_stale=true"))
    assert "stale" in caplog.text and isinstance(rnn, torch.nn.Module)


def test_validation_draws_inputs_as_training_does(stage_cfg, with_vae):
    """best.pt is chosen on the validation loss, so it must see the inputs training sees (rnn.sample_inputs)."""
    for sample_inputs in (False, True):
        cfg = stage_cfg("train_rnn", *NO_DREAMS, f"rnn.sample_inputs={str(sample_inputs).lower()}")
        artifacts.retire(cfg, with_vae / "runs/t/rnn")
        metrics = train_rnn.run(cfg)
        model, _ = loading.load_rnn(cfg)
        store = loading.open_rollouts(cfg)
        lat = Latents(artifacts.latents_path(cfg))
        L, D, B = int(cfg.rnn.seq_len), int(cfg.vae.latent_dim), int(cfg.rnn.batch_size)
        units = train_rnn.windows(store.lengths, store.episodes("validation"), L)
        same = train_rnn.validation_loss(model, lat, units, L, D, B, int(cfg.seed), sample_inputs=sample_inputs)
        other = train_rnn.validation_loss(model, lat, units, L, D, B, int(cfg.seed), sample_inputs=not sample_inputs)
        z, _, _, mask = train_rnn.make_batch(
            lat, units[:2], L, D, torch.Generator().manual_seed(0), sample_inputs=sample_inputs
        )
        mu = np.zeros(z.shape, np.float32)
        for b, (i, s, n) in enumerate(units[:2]):
            mu[b, :n] = lat.episode(i, slice(s, s + n))[0]
        lat.close()
        assert metrics["validation_loss"] == pytest.approx(same, rel=1e-6) and same != other
        assert np.array_equal(z.numpy()[mask.numpy()], mu[mask.numpy()]) is (not sample_inputs)


def test_train_resume_continue(stage_cfg, with_vae):
    train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS, "rnn.epochs=1"))
    one = torch.load(with_vae / "runs/t/rnn/last.pt", weights_only=False)
    train_rnn.run(stage_cfg("train_rnn", *NO_DREAMS, "rnn.epochs=3", "resume=true"))
    three = torch.load(with_vae / "runs/t/rnn/last.pt", weights_only=False)
    assert three["epoch"] == 3 and three["step"] == 3 * one["step"]
    assert {int(s["step"]) for s in three["optimizer"]["state"].values()} == {3 * one["step"]}
    with pytest.raises(StageError, match="hidden"):
        loading.load_rnn(stage_cfg("train_rnn", *NO_DREAMS, "rnn.hidden=256"))


def test_sequence_windows_cover_every_transition_once():
    lengths = {0: 10, 1: 3, 2: 2}
    units = train_rnn.windows(lengths, [0, 1, 2], 4)
    covered = sorted((i, s + k) for i, s, n in units for k in range(n))
    assert covered == [(i, t) for i in (0, 1, 2) for t in range(lengths[i] - 1)]


def test_streamed_encoding_equals_encoding_each_episode(stage_cfg, smoke_builds, tmp_path, dead_pid):
    """Fixed-size batches straddle episode boundaries (batch 7 against episodes of ~45 frames) and the padded
    last batch is dropped, yet every episode gets exactly its own frames' latents and actions."""
    from worldmodel.latents import encode_dataset

    cfg = stage_cfg("train_rnn", root=smoke_builds("vae"))
    vae, vae_path = loading.load_vae(cfg, "best")
    store = loading.open_rollouts(cfg)
    out = tmp_path / "streamed.h5"
    leftover = tmp_path / f".streamed.h5.tmp-{dead_pid}"  # what a killed encoder leaves behind
    leftover.write_bytes(b"half a file")
    encode_dataset(store, vae, vae_path, out, batch_size=7, progress=False)
    assert not leftover.exists()
    lat = Latents(out)
    episodes = sorted(store.location)
    assert sorted(int(k.split("_")[-1]) for k in lat.f.keys()) == episodes
    assert sum(store.lengths.values()) % 7 != 0  # the last batch really is padded
    with torch.inference_mode():
        for i in episodes:
            mu, logvar, action = lat.episode(i)
            ref_mu, ref_logvar = vae.encode(torch.from_numpy(store.read(i, "seg")))
            np.testing.assert_allclose(mu, ref_mu.numpy(), rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(logvar, ref_logvar.numpy(), rtol=1e-4, atol=1e-5)
            np.testing.assert_array_equal(action, store.read(i, "action").astype(np.float32))
    lat.close()
