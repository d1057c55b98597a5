"""The batch-1 decision paths (``worldmodel.models.fast_decision``: fast and module) against the modules.

Every check runs the reference computation the agent's input is defined by, ``SegVAE.encode`` (mu),
``WorldRNN.step`` + ``WorldRNN.predict`` on (z_t, a_{t-1}) and ``torch.tanh(actor.net(x))``, beside the fast path
over whole sequences with the LSTM state carried, so a wrong tap order, gate order, flatten order, bias or
state update shows up as a mismatch far above float rounding (~1e-7 here).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import UrbanCollisionEnv, sample_scenario
from worldmodel.agent_obs import LearnedPolicy, WorldModelEncoder, WorldModelView
from worldmodel.models.ddpg import Actor
from worldmodel.models.fast_decision import FastDecision, ModuleDecision, decision_path
from worldmodel.models.rnn import HEADS, WorldRNN
from worldmodel.models.vae import SegVAE

torch.set_num_threads(1)

# Observed differences are <= 3e-7 (summation order only); a real error is orders of magnitude larger.
TOL = {"rtol": 1e-5, "atol": 2e-6}


def make_models(
    seed: int, head: str = "mdn", residual: bool = True, use_speed: bool = False, hidden: int = 512, channels: int = 32
):
    torch.manual_seed(seed)
    vae = SegVAE(num_classes=13, latent_dim=128, channels=channels)
    rnn = WorldRNN(latent_dim=128, action_dim=2, hidden=hidden, head=head, gaussians=5, residual=residual)
    actor = Actor(256 + int(use_speed), 2)
    # Actor's final layer starts near zero (Lillicrap); spread it so actions span tanh's sensitive range and
    # an error upstream moves them measurably.
    torch.nn.init.normal_(actor.net[-1].weight, std=0.3)
    return vae, rnn, actor


class Reference:
    """The agent's input and action computed with the modules' own batch forward passes."""

    def __init__(self, vae, rnn, actor, use_speed: bool = False):
        self.vae, self.rnn, self.actor, self.use_speed = vae, rnn, actor, use_speed
        self.reset()

    def reset(self):
        self.state = self.rnn.initial_state(1)
        self.prev_action = torch.zeros(1, 2)

    @torch.no_grad()
    def encode(self, obs) -> torch.Tensor:
        z, _ = self.vae.encode(torch.as_tensor(obs["seg"]).unsqueeze(0))
        out, self.state = self.rnn.step(z, self.prev_action, self.state)
        parts = [z, self.rnn.predict(out)]
        if self.use_speed:
            parts.append(torch.as_tensor(obs["speed"], dtype=torch.float32).reshape(1, 1) / 30.0)
        return torch.cat(parts, dim=1)

    @torch.no_grad()
    def act(self, obs) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.encode(obs)
        action = self.actor(x)
        self.prev_action = action
        return x, action


@pytest.fixture(scope="module")
def real_episodes():
    """Segmentation frames from the real simulator (camera on): 3 scenarios under varied steering/braking."""
    env = UrbanCollisionEnv(camera=True)
    rng = np.random.default_rng(7)
    episodes = []
    for k in range(3):
        obs, _ = env.reset(options={"scenario": sample_scenario(np.random.default_rng(100 + k))})
        frames = [{"seg": obs["seg"].copy(), "speed": obs["speed"].copy()}]
        for _ in range(24):
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
            frames.append({"seg": obs["seg"].copy(), "speed": obs["speed"].copy()})
            if terminated or truncated:
                break
        episodes.append(frames)
    env.close()
    return episodes


def random_maps(n: int, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [
        {"seg": rng.integers(0, 13, (64, 64), dtype=np.uint8), "speed": rng.uniform(0, 30, 1).astype(np.float32)}
        for _ in range(n)
    ]


def assert_policy_matches(policy: LearnedPolicy, ref: Reference, episodes) -> None:
    for frames in episodes:
        policy.reset()
        ref.reset()
        for t, obs in enumerate(frames):
            action = policy.act(obs, {})
            want_x, want_a = ref.act(obs)
            got_x = policy.encoder.decision.out  # the input the action was computed from
            D = ref.vae.latent_dim
            torch.testing.assert_close(got_x[:, :D], want_x[:, :D], **TOL, msg=lambda m, t=t: f"z at step {t}: {m}")
            torch.testing.assert_close(got_x[:, D:], want_x[:, D:], **TOL, msg=lambda m, t=t: f"zhat at step {t}: {m}")
            for got, want, name in zip(policy.encoder.state, ref.state, ("h", "c")):
                torch.testing.assert_close(
                    got, want, **TOL, msg=lambda m, t=t, name=name: f"LSTM {name} at step {t}: {m}"
                )
            torch.testing.assert_close(
                torch.from_numpy(action), want_a[0], **TOL, msg=lambda m, t=t: f"action at step {t}: {m}"
            )


def test_real_frames_match_modules_over_episodes(real_episodes):
    vae, rnn, actor = make_models(0)
    ref = Reference(vae, rnn, actor)
    policy = LearnedPolicy("fast", WorldModelEncoder(vae, rnn), actor)
    # the frames must exercise the map: most classes, and a scene that changes over the episode
    frames = [f["seg"] for e in real_episodes for f in e]
    assert len(np.unique(np.stack(frames))) >= 10 and np.median([len(np.unique(f)) for f in frames]) >= 5
    assert any(not np.array_equal(e[0]["seg"], e[-1]["seg"]) for e in real_episodes)
    assert_policy_matches(policy, ref, real_episodes)


@pytest.mark.parametrize("head", HEADS)
@pytest.mark.parametrize("residual", [True, False])
@pytest.mark.parametrize("use_speed", [False, True])
@pytest.mark.parametrize("path", ["fast", "module"])
def test_random_maps_match_modules_for_every_head(head, residual, use_speed, path):
    vae, rnn, actor = make_models(1, head, residual, use_speed)
    ref = Reference(vae, rnn, actor, use_speed)
    policy = LearnedPolicy(path, WorldModelEncoder(vae, rnn, use_speed=use_speed, path=path), actor, path=path)
    assert policy.encoder.path == path
    assert_policy_matches(policy, ref, [random_maps(12, 0), random_maps(5, 1)])


def test_auto_takes_the_fast_path_when_it_passes_its_self_test(real_episodes):
    vae, rnn, actor = make_models(12)
    encoder = WorldModelEncoder(vae, rnn)
    assert encoder.path == "fast" and isinstance(encoder.decision, FastDecision)
    fast, module = (
        LearnedPolicy("a", encoder, actor),
        LearnedPolicy("b", WorldModelEncoder(vae, rnn, path="module"), actor, path="module"),
    )
    for obs in real_episodes[0]:
        np.testing.assert_allclose(fast.act(obs, {}), module.act(obs, {}), **TOL)


def test_auto_falls_back_to_the_module_path_where_the_fast_one_cannot_run(caplog):
    """The fast path packs two class ids into a byte, so a 17-class VAE is beyond it: a real failure of its
    build, which ``auto`` answers with the module path (same numbers) and a warning, and ``fast`` refuses."""
    torch.manual_seed(13)
    vae = SegVAE(num_classes=17, latent_dim=16)
    rnn = WorldRNN(latent_dim=16, action_dim=2, hidden=32, head="mdn", gaussians=3, residual=True)
    actor = Actor(32, 2)
    with caplog.at_level("WARNING"):
        encoder = WorldModelEncoder(vae, rnn)
    assert encoder.path == "module" and isinstance(encoder.decision, ModuleDecision)
    assert "fast decision path is unavailable" in caplog.text and "16 classes" in caplog.text
    with pytest.raises(ValueError, match="16 classes"):
        decision_path(vae, rnn, path="fast")
    rng = np.random.default_rng(4)
    maps = [{"seg": rng.integers(0, 17, (64, 64), dtype=np.uint8), "speed": np.ones(1, np.float32)} for _ in range(5)]
    assert_policy_matches(LearnedPolicy("m", encoder, actor), Reference(vae, rnn, actor), [maps])
    with pytest.raises(ValueError, match="decision path"):
        decision_path(vae, rnn, path="quick")


def test_missing_private_onednn_ops_keep_the_fast_path_on_mkl(real_episodes):
    vae, rnn, actor = make_models(14)
    decision = decision_path(vae, rnn, onednn_ops=("_no_such_op_in_any_torch",))
    assert isinstance(decision, FastDecision) and not decision.onednn
    encoder = WorldModelEncoder(vae, rnn)
    encoder.decision = decision
    assert_policy_matches(LearnedPolicy("mkl", encoder, actor), Reference(vae, rnn, actor), real_episodes[:1])


@pytest.mark.parametrize("onednn", [False, True])
def test_both_matrix_backends_match_modules(real_episodes, onednn):
    """The im2col products run on pre-packed oneDNN weights where available, else on MKL's addmm."""
    if onednn and not FastDecision(*make_models(0)[:2]).onednn:
        pytest.skip("this torch build has no oneDNN linear")
    vae, rnn, actor = make_models(9)
    encoder = WorldModelEncoder(vae, rnn)
    encoder.decision = FastDecision(vae, rnn, onednn=onednn)
    assert_policy_matches(LearnedPolicy("fast", encoder, actor), Reference(vae, rnn, actor), real_episodes[:2])


def test_wrapper_path_with_env_actions_matches_modules(real_episodes):
    """``WorldModelView``'s order: encode(obs_t) with a_{t-1}, then ``note_action(a_t)`` from outside."""
    vae, rnn, actor = make_models(2)
    ref = Reference(vae, rnn, actor)
    encoder = WorldModelEncoder(vae, rnn)
    rng = np.random.default_rng(3)
    first = None
    for frames in real_episodes:
        encoder.reset()
        ref.reset()
        for obs in frames:
            got = encoder.encode(obs)
            first = got if first is None else first
            torch.testing.assert_close(torch.from_numpy(got), ref.encode(obs)[0], **TOL)
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            encoder.note_action(a)
            ref.prev_action = torch.from_numpy(a).reshape(1, 2)
    # returned observations are copies: later frames must not overwrite what a replay buffer holds
    assert got is not first and not np.array_equal(got, first)


def test_same_results_after_loading_checkpoints_the_way_the_agent_does(stage_cfg, real_episodes):
    from worldmodel import artifacts, loading
    from worldmodel.common import atomic_torch_save

    cfg = stage_cfg("train_agent")
    vae, rnn, actor = make_models(
        3, str(cfg.rnn.head), bool(cfg.rnn.residual), hidden=int(cfg.rnn.hidden), channels=int(cfg.vae.channels)
    )
    state = {"model": vae.state_dict(), "latent_dim": vae.latent_dim, "channels": vae.channels}
    atomic_torch_save(state, artifacts.vae_dir(cfg) / "best.pt")
    atomic_torch_save(
        {
            "model": rnn.state_dict(),
            "latent_dim": rnn.latent_dim,
            "hidden": rnn.hidden,
            "head": rnn.head,
            "residual": rnn.residual,
            "provenance": {"inputs": {"vae": artifacts.vae_id(cfg)}},
        },
        artifacts.rnn_dir(cfg) / "best.pt",
    )
    encoder = loading.load_world_model(cfg)
    assert encoder.vae is not vae  # freshly built modules, weights only from the files
    policy = LearnedPolicy("fast", encoder, actor)
    assert_policy_matches(policy, Reference(vae, rnn, actor), real_episodes[:2])


def test_weights_changed_after_construction_are_used():
    """load_state_dict, optimiser-style in-place updates and actor training must not leave a stale copy."""
    vae, rnn, actor = make_models(4)
    policy = LearnedPolicy("fast", WorldModelEncoder(vae, rnn), actor)
    maps = [random_maps(6, 5)]
    assert_policy_matches(policy, Reference(vae, rnn, actor), maps)

    other_vae, other_rnn, other_actor = make_models(5)
    vae.load_state_dict(other_vae.state_dict())
    rnn.load_state_dict(other_rnn.state_dict())
    actor.load_state_dict(other_actor.state_dict())
    assert_policy_matches(policy, Reference(other_vae, other_rnn, other_actor), maps)

    with torch.no_grad():
        vae.enc1.bias.add_(0.5)  # a layer folded into a lookup table
        rnn.lstm.weight_hh_l0.mul_(1.5)
        rnn.fc.bias.sub_(0.2)
        actor.net[0].weight.mul_(-1.0)
    assert_policy_matches(policy, Reference(vae, rnn, actor), maps)


def test_grad_modes_of_the_caller_do_not_matter():
    """Built or called under inference_mode / enable_grad: same numbers, no autograd graph, no error."""
    vae, rnn, actor = make_models(10)
    maps = [random_maps(4, 12)]
    with torch.inference_mode():
        policy = LearnedPolicy("fast", WorldModelEncoder(vae, rnn), actor)
    assert_policy_matches(policy, Reference(vae, rnn, actor), maps)
    with torch.inference_mode():
        assert_policy_matches(policy, Reference(vae, rnn, actor), maps)
    with torch.enable_grad():
        policy.act(maps[0][0], {})
        assert not policy.encoder.decision.out.requires_grad
    # a rebuild triggered inside inference_mode (act) must leave buffers usable outside it (encode_tensor)
    for onednn in (False, True):
        encoder = WorldModelEncoder(vae, rnn)
        encoder.decision = FastDecision(vae, rnn, onednn=onednn and FastDecision(vae, rnn).onednn)
        policy = LearnedPolicy("fast", encoder, actor)
        with torch.no_grad():
            vae.enc3.weight.mul_(0.9)
        policy.act(maps[0][0], {})
        got = encoder.encode_tensor(maps[0][1]).clone()
        ref = Reference(vae, rnn, actor)
        ref.act(maps[0][0])
        torch.testing.assert_close(got, ref.encode(maps[0][1]), **TOL)


def test_bad_class_maps_are_rejected():
    vae, rnn, _ = make_models(6)
    encoder = WorldModelEncoder(vae, rnn)
    seg = np.zeros((64, 64), np.uint8)
    seg[10, 11] = 13  # an id the pair lookup would otherwise misread as a valid neighbouring entry
    with pytest.raises(ValueError, match=r"class ids must lie in \[0, 13\)"):
        encoder.encode({"seg": seg})
    with pytest.raises(ValueError, match="class ids"):
        encoder.encode({"seg": np.full((64, 64), -1, np.int64)})
    with pytest.raises(ValueError, match="integer class map"):
        encoder.encode({"seg": np.zeros((64, 64), np.float32)})
    with pytest.raises(ValueError, match="integer class map"):
        encoder.encode({"seg": np.zeros((32, 64), np.uint8)})
    # int64 maps are the same map as uint8
    maps = random_maps(1, 9)[0]["seg"]
    a = encoder.encode({"seg": maps})
    encoder.reset()
    np.testing.assert_array_equal(encoder.encode({"seg": maps.astype(np.int64)}), a)


def test_wrapped_env_observations_match_modules():
    """End to end through ``WorldModelView`` on the real env (camera on), stepping with fixed actions."""
    vae, rnn, actor = make_models(8)
    ref = Reference(vae, rnn, actor)
    view = WorldModelView(UrbanCollisionEnv(camera=True), WorldModelEncoder(vae, rnn))
    spec = sample_scenario(np.random.default_rng(11))
    obs, _ = view.reset(options={"scenario": spec})
    raw = UrbanCollisionEnv(camera=True)
    raw_obs, _ = raw.reset(options={"scenario": spec})
    torch.testing.assert_close(torch.from_numpy(obs), ref.encode(raw_obs)[0], **TOL)
    for k in range(10):
        a = np.array([np.sin(k), -0.5], np.float32)
        obs, *_ = view.step(a)
        raw_obs, *_ = raw.step(a)
        ref.prev_action = torch.from_numpy(a).reshape(1, 2)
        torch.testing.assert_close(torch.from_numpy(obs), ref.encode(raw_obs)[0], **TOL)
    view.close()
    raw.close()
