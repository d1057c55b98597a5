"""What the world model dreams (worldmodel/dreams.py): the action-effect metric against the real simulator, quality
against horizon, and the multi-step loss, on the real scene and the session's smoke-scale world model."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from worldmodel import artifacts, dreams, loading, train_rnn
from worldmodel.common import make_env
from worldmodel.latents import Latents


@pytest.fixture(scope="module")
def bank(smoke_builds):
    from worldmodel.config import compose

    root = smoke_builds("rnn")
    cfg = compose(
        "train_rnn", [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"]
    )
    env = make_env(cfg, camera=True)
    try:
        first = dreams.branch_bank(env, points=3, horizon=6, warmup=4, seed=5)
        again = dreams.branch_bank(env, points=3, horizon=6, warmup=4, seed=5)
    finally:
        env.close()
    return cfg, first, again


def test_branch_bank_is_reproducible_and_branches_start_from_one_state(bank):
    _, first, again = bank
    for key in first:
        assert np.array_equal(first[key], again[key]), key
    assert first["seg"].shape[:3] == (3, len(dreams.ACTIONS), 6)
    assert first["context_seg"].shape[1] == 5 and first["context_action"].shape[1:] == (4, 2)
    assert sorted(set(first["speed"])) == [10.0, 20.0]


def test_the_metric_is_zero_for_identical_branches_and_positive_for_real_ones(bank):
    _, real, _ = bank
    same = np.repeat(real["seg"][:, :1], len(dreams.ACTIONS), axis=1)
    zero = dreams.action_effect(same, same, real["valid"])
    for entry in zero["actions"].values():
        assert all(x == 0 for key in entry["real"] for x in entry["real"][key])
        assert all(r is None for r in entry["ratio"]["all"])  # no real effect: no ratio, not a division by zero
    effect = dreams.action_effect(real["seg"], real["seg"], real["valid"])
    for name in ("left", "right", "brake"):
        assert effect["actions"][name]["real"]["all"][-1] > 0, name
        assert effect["actions"][name]["ratio"]["all"][-1] == pytest.approx(1.0)
    # steering moves the picture more than braking does within 0.4 s
    assert effect["actions"]["left"]["real"]["all"][-1] > effect["actions"]["brake"]["real"]["all"][-1]
    # a world model that dreams "keep" whatever the action captures none of the effect
    blind = dreams.action_effect(real["seg"], same, real["valid"])
    assert blind["actions"]["left"]["ratio"]["all"][-1] == 0.0


def test_dreams_start_from_the_branch_point_and_follow_the_action_input(bank):
    cfg, real, _ = bank
    vae, _ = loading.load_vae(cfg)
    rnn, _ = loading.load_rnn(cfg)
    dreamt = dreams.dream_branches(vae, rnn, real)
    assert dreamt.shape == real["seg"].shape and dreamt.dtype == np.uint8
    # with the action's weights zeroed, every action dreams the same future
    with torch.no_grad():
        rnn.lstm.weight_ih_l0[:, -2:] = 0
    deaf = dreams.dream_branches(vae, rnn, real)
    assert (deaf == deaf[:, :1]).all()


def test_an_untrained_residual_lstm_dreams_decoded_persistence(smoke_builds):
    from worldmodel.config import compose

    root = smoke_builds("rnn")
    cfg = compose(
        "train_rnn", [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"]
    )
    vae, _ = loading.load_vae(cfg)
    rnn = loading.build_rnn(cfg.vae, cfg.rnn).eval()
    with torch.no_grad():
        rnn.fc.weight.zero_()
        rnn.fc.bias.zero_()
    store = loading.open_rollouts(cfg)
    lat = Latents(artifacts.latents_path(cfg))
    try:
        q = dreams.horizon_quality(vae, rnn, store, lat, store.episodes("train", branches=False), horizon=3, every=2)
    finally:
        lat.close()
    assert q["starts"][0] > 0
    assert q["lstm"]["pixel_accuracy"] == q["persistence_vae"]["pixel_accuracy"]
    assert not any(dreams.beats_decoded_persistence(q).values())


def test_the_stage_reports_action_effect_and_horizon(smoke_builds):
    metrics = json.loads((smoke_builds("rnn") / "runs/t/rnn/metrics.json").read_text())
    effect = metrics["action_effect"]
    assert effect["points"] == 2 and effect["horizons"] == [1, 2, 3, 4]
    assert set(effect["actions"]) == set(dreams.ACTIONS) - {"keep"}
    for entry in effect["actions"].values():
        assert set(entry["real"]) == {"all", "vehicles", "pedestrians", "roads"}
    # the points behind it are written beside, and give it again
    rows = dreams.read_effect_rows(smoke_builds("rnn") / "runs/t/rnn/action_effect.rows.csv.gz")
    assert {r["point"] for r in rows} <= {0, 1}
    assert dreams.summarise_effect(rows, 4, 2) == json.loads(json.dumps(effect))
    horizon = metrics["horizon"]
    assert set(dreams.HORIZON_KEYS) <= set(horizon) and len(horizon["lstm"]["pixel_accuracy"]) == 4
    assert set(horizon["lstm_beats_decoded_persistence"]) == {"pixel_accuracy", "hazard_iou"}


def test_open_loop_loss_of_one_step_is_the_teacher_forced_loss():
    torch.manual_seed(0)
    rnn = artifacts_free_rnn()
    z, a = torch.randn(3, 6, 8), torch.rand(3, 6, 2) * 2 - 1
    z_next = torch.randn(3, 6, 8)
    mask = torch.ones(3, 6, dtype=torch.bool)
    mask[2, 4:] = False
    out, _ = rnn(z, a)
    for start in (0, 2, 5):
        forced = train_rnn.masked_loss(
            rnn,
            {k: v[:, start : start + 1] for k, v in out.items()},
            z_next[:, start : start + 1],
            mask[:, start : start + 1],
        )
        assert train_rnn.open_loop_loss(rnn, z, a, z_next, mask, start, 1).item() == pytest.approx(
            forced.item(), rel=1e-5
        )
    # two steps: the second is predicted from the first prediction, not from the real z
    two = train_rnn.open_loop_loss(rnn, z, a, z_next, mask, 2, 2)
    forced_two = train_rnn.masked_loss(rnn, {k: v[:, 2:4] for k, v in out.items()}, z_next[:, 2:4], mask[:, 2:4])
    assert two.item() != pytest.approx(forced_two.item(), rel=1e-4)
    # nothing valid in the window: no loss, not NaN
    assert train_rnn.open_loop_loss(rnn, z, a, z_next, torch.zeros_like(mask), 1, 3).item() == 0.0


def artifacts_free_rnn():
    from worldmodel.models.rnn import WorldRNN

    return WorldRNN(latent_dim=8, hidden=16, head="mdn", gaussians=3)


def test_a_perfect_dream_matches_every_branch_and_a_blind_one_only_keep(bank):
    _, real, _ = bank
    effect = dreams.action_effect(real["seg"], real["seg"], real["valid"])
    for name, entry in effect["actions"].items():
        assert entry["match"] == pytest.approx([1.0] * 6), name
        assert entry["blind_match"][-1] < 1.0, name  # keep's future is not the swerve's or the brake's


def test_the_direction_score_credits_only_the_true_class_on_the_pixels_the_action_changed(bank, tmp_path):
    """A perfect dream shows every changed pixel in its true class, a dream that ignores the action none (there,
    the real frame under the action differs from the real 'keep' frame by definition); the intervals hold the
    point estimate; the rows, written and read back, give the same summary."""
    _, real, _ = bank
    same = np.repeat(real["seg"][:, :1], len(dreams.ACTIONS), axis=1)
    rows = dreams.effect_rows(real["seg"], real["seg"], real["valid"], recon_seg=real["seg"], speed=real["speed"])
    perfect = dreams.summarise_effect(rows, 6, 3, boot=200)
    blind = dreams.action_effect(real["seg"], same, real["valid"], recon_seg=real["seg"], boot=200)
    assert set(perfect["actions"]) == set(dreams.ACTIONS) - {"keep"}
    for name in ("left", "right_half", "brake_right"):
        direction = perfect["actions"][name]["direction"]
        assert direction["dream"]["score"][-1] == 1.0 and direction["vae"]["score"][-1] == 1.0, name
        assert direction["blind"]["score"][-1] == 0.0, name
        assert blind["actions"][name]["direction"]["dream"]["score"][-1] == 0.0, name
        low, high = perfect["actions"][name]["ratio_ci95"][-1]
        assert low <= perfect["actions"][name]["ratio"]["all"][-1] <= high, name
    dreams.write_effect_rows(rows, tmp_path / "rows.csv.gz")
    assert dreams.summarise_effect(dreams.read_effect_rows(tmp_path / "rows.csv.gz"), 6, 3, boot=200) == perfect
    text = "\n".join(dreams.effect_headline_markdown(perfect))
    assert "| left_half | +5 |" in text and "| brake_right | +5 |" in text
