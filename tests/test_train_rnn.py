"""Phase 2 on real smoke-scale data: encoding cache, resume, errors."""
from __future__ import annotations

import os

import pytest
import torch

from worldmodel import collect, train_rnn, train_vae
from worldmodel.common import StageError


@pytest.fixture
def with_vae(stage_cfg):
    collect.run(stage_cfg("collect"))
    train_vae.run(stage_cfg("train_vae", "vae.batch_size=8"))


def test_missing_vae_names_the_command(stage_cfg):
    with pytest.raises(StageError, match="worldmodel.train_vae experiment=t"):
        train_rnn.run(stage_cfg("train_rnn"))


def test_reencodes_only_when_the_vae_checkpoint_changes(stage_cfg, with_vae, tmp_path):
    cfg = stage_cfg("train_rnn")
    first = train_rnn.run(cfg)
    assert first["reencoded_latents"] is True
    latents = tmp_path / "data/t/latents.h5"
    stamp = latents.stat().st_mtime_ns

    # Same VAE: the encoding is reused.
    second = train_rnn.run(stage_cfg("train_rnn", "rnn.epochs=2", "resume=true"))
    assert second["reencoded_latents"] is False and latents.stat().st_mtime_ns == stamp

    # The VAE trains one more epoch: its best checkpoint changes, so the dataset is encoded again.
    train_vae.run(stage_cfg("train_vae", "vae.batch_size=8", "vae.epochs=2", "resume=true"))
    os.utime(latents, ns=(stamp, stamp))
    third = train_rnn.run(stage_cfg("train_rnn", "rnn.epochs=2", "resume=true"))
    vae_changed = third["reencoded_latents"]
    best = torch.load(tmp_path / "runs/t/vae/best.pt", weights_only=False)
    assert vae_changed == (best["epoch"] == 2)


def test_train_resume_continue(stage_cfg, with_vae, tmp_path):
    train_rnn.run(stage_cfg("train_rnn", "rnn.epochs=1"))
    one = torch.load(tmp_path / "runs/t/rnn/last.pt", weights_only=False)
    train_rnn.run(stage_cfg("train_rnn", "rnn.epochs=3", "resume=true"))
    three = torch.load(tmp_path / "runs/t/rnn/last.pt", weights_only=False)
    assert three["epoch"] == 3 and three["step"] == 3 * one["step"]
    assert {int(s["step"]) for s in three["optimizer"]["state"].values()} == {3 * one["step"]}


def test_hidden_size_mismatch_is_named(stage_cfg, with_vae):
    train_rnn.run(stage_cfg("train_rnn"))
    with pytest.raises(StageError, match="hidden"):
        train_rnn.load_rnn(stage_cfg("train_rnn", "rnn.hidden=256"))


def test_sequence_windows_cover_every_transition_once():
    lengths = {0: 10, 1: 3, 2: 2}
    units = train_rnn.windows(lengths, [0, 1, 2], 4)
    covered = sorted((i, s + k) for i, s, n in units for k in range(n))
    assert covered == [(i, t) for i in (0, 1, 2) for t in range(lengths[i] - 1)]


def test_streamed_encoding_equals_encoding_each_episode(stage_cfg, with_vae, tmp_path):
    """Fixed-size batches straddle episode boundaries (batch 7 against episodes of ~45 frames) and the padded
    last batch is dropped, yet every episode gets exactly its own frames' latents and actions."""
    import numpy as np

    from worldmodel.latents import Latents, encode_dataset

    cfg = stage_cfg("train_rnn")
    vae, vae_path = train_vae.load_vae(cfg, "best")
    store = train_vae.open_rollouts(cfg)
    out = tmp_path / "streamed.h5"
    encode_dataset(store, vae, vae_path, out, batch_size=7, progress=False)
    lat = Latents(out)
    episodes = sorted(store.location)
    assert sorted(int(k.split("_")[-1]) for k in lat.f.keys()) == episodes
    assert sum(store.lengths.values()) % 7 != 0   # the last batch really is padded
    with torch.inference_mode():
        for i in episodes:
            mu, logvar, action = lat.episode(i)
            ref_mu, ref_logvar = vae.encode(torch.from_numpy(store.read(i, "seg")))
            np.testing.assert_allclose(mu, ref_mu.numpy(), rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(logvar, ref_logvar.numpy(), rtol=1e-4, atol=1e-5)
            np.testing.assert_array_equal(action, store.read(i, "action").astype(np.float32))
    lat.close()
