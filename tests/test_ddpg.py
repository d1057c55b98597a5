"""DDPG: it learns tasks with known answers, its targets and soft updates follow the equations, and
checkpoints restore it exactly. Real networks and optimisers throughout; every test runs in seconds on one thread."""

from __future__ import annotations

import copy
import io
import time

import numpy as np
import pytest
import torch

from worldmodel.models.ddpg import DDPG, Actor, Critic, DDPGConfig, ReplayBuffer
from worldmodel.models.td3 import TD3, make_agent

torch.set_num_threads(1)

SMALL = dict(actor_hidden=(32, 32), critic_hidden=(32, 32), batch_size=16)


def roundtrip(obj):
    """Through bytes, as a checkpoint file would, so nothing aliases the original's tensors."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=False)


def filled_buffer(n: int, obs_dim: int, act_dim: int, seed: int = 0, capacity: int = 1000) -> ReplayBuffer:
    rng = np.random.default_rng(seed)
    buf = ReplayBuffer(capacity, obs_dim, act_dim)
    for _ in range(n):
        buf.add(
            rng.normal(size=obs_dim),
            rng.uniform(-1, 1, act_dim),
            rng.normal(),
            rng.normal(size=obs_dim),
            rng.random() < 0.5,
        )
    return buf


# ----------------------------------------------------------------------------- learning with known answers
W_BANDIT = np.array([[0.9, -0.6, 0.4], [-0.5, 0.7, 0.8]], dtype=np.float32)


def bandit_optimum(s: np.ndarray) -> np.ndarray:
    return np.clip(s @ W_BANDIT.T, -1.0, 1.0)


def test_learns_contextual_bandit_optimal_action():
    """One-step episodes, reward -||a - a*(s)||^2: the actor must end up at a*(s), a known function of s
    (linear where it is inside [-1, 1], saturated outside), using warm-up, exploration, replay and updates."""
    start = time.perf_counter()
    cfg = DDPGConfig(
        actor_hidden=(64, 64),
        critic_hidden=(64, 64),
        actor_lr=1e-3,
        critic_lr=1e-3,
        tau=0.05,
        batch_size=64,
        buffer_size=10_000,
        exploration_noise=0.3,
        warmup_steps=500,
    )
    agent = DDPG(obs_dim=3, act_dim=2, cfg=cfg, seed=0)
    buffer = ReplayBuffer(cfg.buffer_size, 3, 2)
    env_rng = np.random.default_rng(100)
    test_states = env_rng.uniform(-1, 1, (1000, 3)).astype(np.float32)
    error_before = np.abs(agent.act(test_states, explore=False) - bandit_optimum(test_states)).mean()

    s = env_rng.uniform(-1, 1, 3).astype(np.float32)
    for step in range(3000):
        a = agent.random_action() if step < cfg.warmup_steps else agent.act(s, explore=True)
        r = -float(((a - bandit_optimum(s)) ** 2).sum())
        next_s = env_rng.uniform(-1, 1, 3).astype(np.float32)
        buffer.add(s, a, r, next_s, terminated=True)
        s = next_s
        if step >= cfg.warmup_steps:
            info = agent.update(buffer.sample(cfg.batch_size, agent.rng))
            assert all(np.isfinite(v) for v in info.values())

    error_after = np.abs(agent.act(test_states, explore=False) - bandit_optimum(test_states)).mean()
    elapsed = time.perf_counter() - start
    print(f"bandit: mean |a - a*| {error_before:.3f} -> {error_after:.3f} in {elapsed:.1f}s")
    assert error_before > 0.3, "an untrained actor should be far from a*"
    assert error_after < 0.1  # (its time is printed, not asserted: speed belongs to benchmarks/)


@pytest.mark.parametrize("first_step_terminated, expected_q", [(False, [0.64, 0.8, 1.0]), (True, [0.0, 0.8, 1.0])])
def test_bootstraps_through_time_and_stops_at_termination(first_step_terminated, expected_q):
    """Chain s0 -> s1 -> s2, reward 1 - (a - 0.5)^2 only at s2 (terminal), gamma 0.8.

    Stored correctly (s0 -> s1 not terminal, as for a time-limit truncation) the critic must learn the
    discounted values gamma^2, gamma, 1 at the optimal actions. If s0 -> s1 is flagged terminated, the value
    of s0 must drop to 0: the flag, not the data, decides whether the future is counted."""
    cfg = DDPGConfig(
        actor_hidden=(32, 32), critic_hidden=(32, 32), actor_lr=1e-3, critic_lr=1e-3, gamma=0.8, tau=0.05, batch_size=64
    )
    agent = DDPG(obs_dim=3, act_dim=1, cfg=cfg, seed=0)
    states = np.eye(3, dtype=np.float32)
    buffer = ReplayBuffer(1000, 3, 1)
    for _ in range(300):
        for k in range(3):
            a = agent.random_action()
            r = 1.0 - (a[0] - 0.5) ** 2 if k == 2 else 0.0
            terminated = k == 2 or (k == 0 and first_step_terminated)
            buffer.add(states[k], a, r, states[min(k + 1, 2)], terminated)
    for _ in range(1500):
        agent.update(buffer.sample(cfg.batch_size, agent.rng))

    with torch.no_grad():
        obs = torch.from_numpy(states)
        q = agent.critic(obs, agent.actor(obs)).numpy()
    np.testing.assert_allclose(q, expected_q, atol=0.05)
    # The terminal step's optimal action is known; the others do not affect reward.
    assert abs(agent.act(states[2], explore=False)[0] - 0.5) < 0.05


# ----------------------------------------------------------------------------- the update equations
def test_critic_target_and_loss_match_hand_computation():
    cfg = DDPGConfig(**SMALL, gamma=0.9)
    agent = DDPG(obs_dim=4, act_dim=2, cfg=cfg, seed=1)
    # Make the target networks differ from the online ones so the test sees which networks the target uses.
    for _ in range(5):
        agent.update(filled_buffer(64, 4, 2, seed=2).sample(16, agent.rng))
    batch = filled_buffer(64, 4, 2, seed=3).sample(16, np.random.default_rng(0))
    batch["terminated"] = torch.tensor([1.0, 0.0] * 8)

    with torch.no_grad():
        next_q = agent.critic_target(batch["next_obs"], agent.actor_target(batch["next_obs"]))
        q = agent.critic(batch["obs"], batch["actions"])
    expected = batch["rewards"] + 0.9 * (1 - batch["terminated"]) * next_q
    y = agent.td_target(batch)

    done = batch["terminated"] == 1
    assert torch.equal(y[done], batch["rewards"][done]), "a terminal transition's target is exactly r"
    torch.testing.assert_close(y[~done], batch["rewards"][~done] + 0.9 * next_q[~done])
    assert (y[~done] - batch["rewards"][~done]).abs().min() > 1e-4, "non-terminal targets must include gamma*Q'"
    torch.testing.assert_close(y, expected)

    # ... and update() regresses onto exactly that target.
    info = agent.update(batch)
    assert info["critic_loss"] == pytest.approx(((q - expected) ** 2).mean().item(), rel=1e-5)
    assert info["q_mean"] == pytest.approx(q.mean().item(), rel=1e-5)


def test_actor_loss_is_minus_q_of_actor_action_and_improves_it():
    agent = DDPG(obs_dim=4, act_dim=2, cfg=DDPGConfig(**SMALL, actor_lr=1e-2), seed=4)
    batch = filled_buffer(64, 4, 2).sample(16, np.random.default_rng(0))
    actor_before = copy.deepcopy(agent.actor)
    info = agent.update(batch)
    # The actor is scored by the critic as it stands after this update's critic step.
    with torch.no_grad():
        q_before = agent.critic(batch["obs"], actor_before(batch["obs"])).mean().item()
        q_after = agent.critic(batch["obs"], agent.actor(batch["obs"])).mean().item()
    assert info["actor_loss"] == pytest.approx(-q_before, rel=1e-5)
    assert q_after > q_before, "one actor step must raise Q(s, mu(s)) under the critic that guided it"


def test_soft_update_moves_targets_by_tau():
    tau = 0.1
    agent = DDPG(obs_dim=4, act_dim=2, cfg=DDPGConfig(**SMALL, tau=tau), seed=5)
    # Separate targets from online networks first, otherwise the check would hold for any tau.
    for _ in range(3):
        agent.update(filled_buffer(64, 4, 2).sample(16, agent.rng))
    old_targets = [copy.deepcopy(agent.actor_target), copy.deepcopy(agent.critic_target)]
    agent.update(filled_buffer(64, 4, 2, seed=1).sample(16, agent.rng))

    for old, new_online, new_target in zip(
        old_targets, (agent.actor, agent.critic), (agent.actor_target, agent.critic_target)
    ):
        for p_old, p_online, p_target in zip(old.parameters(), new_online.parameters(), new_target.parameters()):
            assert not torch.allclose(p_old, p_online), "targets and online networks must differ for this test"
            torch.testing.assert_close(p_target, (1 - tau) * p_old + tau * p_online)
    assert not any(p.requires_grad for p in agent.actor_target.parameters())


# ----------------------------------------------------------------------------- acting
def test_act_shapes_range_and_noise():
    agent = DDPG(obs_dim=5, act_dim=3, cfg=DDPGConfig(**SMALL, exploration_noise=0.2), seed=6)
    obs = np.random.default_rng(0).normal(size=(2000, 5)).astype(np.float32)
    greedy = agent.act(obs, explore=False)
    assert greedy.shape == (2000, 3) and greedy.dtype == np.float32
    np.testing.assert_array_equal(greedy, agent.act(obs, explore=False))
    single = agent.act(obs[0], explore=False)
    assert single.shape == (3,) and single.dtype == np.float32
    np.testing.assert_allclose(single, greedy[0], atol=1e-6)

    noisy = agent.act(obs, explore=True)
    assert noisy.dtype == np.float32 and noisy.min() >= -1 and noisy.max() <= 1
    # The initial actor outputs ~0, so the noise is barely clipped and its std shows through.
    assert abs((noisy - greedy).std() - 0.2) < 0.01

    big = DDPG(obs_dim=5, act_dim=3, cfg=DDPGConfig(**SMALL, exploration_noise=5.0), seed=6)
    assert np.abs(big.act(obs, explore=True)).max() == 1.0

    uniform = np.stack([agent.random_action() for _ in range(2000)])
    assert uniform.shape == (2000, 3) and uniform.dtype == np.float32
    assert uniform.min() >= -1 and uniform.max() <= 1
    assert abs(uniform.mean()) < 0.05 and abs(uniform.var() - 1 / 3) < 0.03


def test_initial_outputs_are_small():
    torch.manual_seed(0)
    obs, act = torch.randn(256, 6), torch.rand(256, 2) * 2 - 1
    assert Actor(6, 2).forward(obs).abs().max() < 0.05
    assert Critic(6, 2).forward(obs, act).shape == (256,)
    assert Critic(6, 2).forward(obs, act).abs().max() < 0.05


def test_same_seed_same_agent_and_global_torch_rng_untouched():
    torch.manual_seed(123)
    expected_next = torch.rand(3)
    torch.manual_seed(123)
    a = DDPG(obs_dim=4, act_dim=2, cfg=DDPGConfig(**SMALL), seed=7)
    assert torch.equal(torch.rand(3), expected_next), "building an agent must not consume the global torch RNG"
    b = DDPG(obs_dim=4, act_dim=2, cfg=DDPGConfig(**SMALL), seed=7)
    c = DDPG(obs_dim=4, act_dim=2, cfg=DDPGConfig(**SMALL), seed=8)
    obs = np.ones(4, dtype=np.float32)
    np.testing.assert_array_equal(a.act(obs, explore=True), b.act(obs, explore=True))
    assert not np.array_equal(a.act(obs, explore=False), c.act(obs, explore=False))


# ----------------------------------------------------------------------------- replay buffer
def test_replay_buffer_wraps_around_and_samples_filled_part():
    buf = ReplayBuffer(capacity=5, obs_dim=2, act_dim=1)
    with pytest.raises(ValueError):
        buf.sample(4, np.random.default_rng(0))
    for i in range(3):
        buf.add([i, i], [0.1 * i], float(i), [i + 1, i + 1], i == 2)
    assert len(buf) == 3
    seen = buf.sample(200, np.random.default_rng(0))["rewards"].numpy()
    assert set(seen.tolist()) == {0.0, 1.0, 2.0}, "only filled slots may be sampled"

    for i in range(3, 7):
        buf.add([i, i], [0.1 * i], float(i), [i + 1, i + 1], i == 6)
    assert len(buf) == 5 and buf.pos == 2
    # The two oldest (0, 1) were overwritten in place by the two newest (5, 6).
    np.testing.assert_array_equal(buf.rewards, [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(buf.obs[:, 0], [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(buf.next_obs[:, 0], [6, 7, 3, 4, 5])
    np.testing.assert_array_equal(buf.terminated, [0, 1, 1, 0, 0])

    batch = buf.sample(300, np.random.default_rng(1))
    assert set(batch["rewards"].numpy().tolist()) == {2.0, 3.0, 4.0, 5.0, 6.0}
    assert {k: v.dtype for k, v in batch.items()} == dict.fromkeys(ReplayBuffer.FIELDS, torch.float32)
    assert batch["obs"].shape == (300, 2) and batch["actions"].shape == (300, 1) and batch["rewards"].shape == (300,)
    # Rows stay aligned: next_obs = obs + 1 and reward = obs for every stored transition.
    torch.testing.assert_close(batch["next_obs"], batch["obs"] + 1)
    torch.testing.assert_close(batch["rewards"], batch["obs"][:, 0])
    # Sampled tensors are copies: later adds must not change a batch already handed out.
    before = batch["obs"].clone()
    for _ in range(5):
        buf.add([-9, -9], [0.0], 0.0, [0, 0], False)
    assert torch.equal(batch["obs"], before)


def test_replay_buffer_state_dict_round_trip():
    buf = filled_buffer(37, obs_dim=3, act_dim=2, capacity=50)
    state = roundtrip(buf.state_dict())
    assert state["obs"].shape == (37, 3), "only the filled part is stored"

    restored = ReplayBuffer(50, 3, 2)
    restored.load_state_dict(state)
    assert len(restored) == 37 and restored.pos == buf.pos
    rng = np.random.default_rng(9)
    rng_copy = np.random.default_rng(9)
    a, b = buf.sample(32, rng), restored.sample(32, rng_copy)
    for key in ReplayBuffer.FIELDS:
        assert torch.equal(a[key], b[key]), key

    # Both continue identically, including across the wrap-around.
    extra = filled_buffer(30, 3, 2, seed=5)
    for i in range(30):
        for target in (buf, restored):
            target.add(extra.obs[i], extra.actions[i], extra.rewards[i], extra.next_obs[i], extra.terminated[i])
    assert len(restored) == 50 and restored.pos == buf.pos == 17
    for key in ReplayBuffer.FIELDS:
        np.testing.assert_array_equal(getattr(buf, key), getattr(restored, key))

    with pytest.raises(ValueError, match="capacity"):
        ReplayBuffer(40, 3, 2).load_state_dict(state)


# ----------------------------------------------------------------------------- checkpoints
def test_agent_state_dict_round_trip_resumes_exactly():
    cfg = DDPGConfig(**SMALL)
    buffer = filled_buffer(200, obs_dim=4, act_dim=2)
    original = DDPG(obs_dim=4, act_dim=2, cfg=cfg, seed=10)
    for _ in range(20):  # non-trivial optimiser moments and diverged targets
        original.update(buffer.sample(cfg.batch_size, original.rng))
    original.act(np.zeros(4, np.float32), explore=True)

    resumed = DDPG(obs_dim=4, act_dim=2, cfg=cfg, seed=999)
    resumed.load_state_dict(roundtrip(original.state_dict()))

    obs = np.random.default_rng(0).normal(size=(8, 4)).astype(np.float32)
    np.testing.assert_array_equal(original.act(obs, explore=False), resumed.act(obs, explore=False))
    # Same generator state: same exploration noise, warm-up actions and minibatch indices.
    np.testing.assert_array_equal(original.act(obs, explore=True), resumed.act(obs, explore=True))
    np.testing.assert_array_equal(original.random_action(), resumed.random_action())
    for _ in range(3):
        info_a = original.update(buffer.sample(cfg.batch_size, original.rng))
        info_b = resumed.update(buffer.sample(cfg.batch_size, resumed.rng))
        assert info_a == info_b
    for name in ("actor", "critic", "actor_target", "critic_target"):
        for pa, pb in zip(getattr(original, name).parameters(), getattr(resumed, name).parameters()):
            assert torch.equal(pa, pb), name

    # Without the optimiser state the next update differs, so the check above is not vacuous.
    partial = roundtrip(original.state_dict())
    fresh_opt = DDPG(obs_dim=4, act_dim=2, cfg=cfg, seed=10)
    partial["critic_optimizer"] = fresh_opt.critic_optimizer.state_dict()
    partial["actor_optimizer"] = fresh_opt.actor_optimizer.state_dict()
    no_moments = DDPG(obs_dim=4, act_dim=2, cfg=cfg, seed=10)
    no_moments.load_state_dict(partial)
    batch = buffer.sample(cfg.batch_size, np.random.default_rng(3))
    original.update(batch)
    no_moments.update(batch)
    assert not torch.equal(original.actor.net[0].weight, no_moments.actor.net[0].weight)


# ----------------------------------------------------------------------------- config
def test_agent_ddpg_section_is_the_ddpg_schema_and_its_old_keys_name_their_new_place():
    """`agent.ddpg` is built from DDPGSettings itself (no second copy of the defaults to drift), typed; a DDPG is
    built from it with the LIDAR observation's shape; an impossible value is named by its full key, and an
    override of a key's old place (`agent.tau`) by its new one."""
    from omegaconf import OmegaConf

    from worldmodel.common import StageError
    from worldmodel.config import AgentConfig, compose, validate
    from worldmodel.models.ddpg_config import DDPGSettings

    section = OmegaConf.to_object(compose("train_agent").agent)
    assert isinstance(section, AgentConfig) and type(section.ddpg) is DDPGSettings
    assert DDPGConfig.of(section) == DDPGConfig()
    assert all(type(w) is int for w in section.ddpg.actor_hidden) and type(section.ddpg.actor_lr) is float
    paper = OmegaConf.to_object(compose("train_agent", ["scale=paper"]).agent)
    assert paper.total_steps == 40000 and paper.ddpg.warmup_steps == 2000 and paper.ddpg.tau == DDPGConfig().tau
    kim = OmegaConf.to_object(compose("train_agent", ["agent=ddpg_kim"]).agent)
    assert (DDPGConfig.of(kim).lidar_scans, DDPGConfig.of(kim).n_step) == (4, 3)
    for override, key in (
        ("agent.ddpg.tau=0", "agent.ddpg.tau=0.0"),
        ("agent.ddpg.actor_hidden=[0,3]", "agent.ddpg.actor_hidden"),
        ("agent.total_steps=-5", "agent.total_steps"),
        ("agent.lidar_rays=4", "agent.lidar_rays"),
        ("agent.dqn.gamma=2", "agent.dqn.gamma=2.0"),  # any nested section, named by its full key
    ):
        with pytest.raises(StageError, match=key):
            validate(compose("train_agent", ["agent.lidar_scans=4", override]))
    with pytest.raises(StageError, match=r"agent.tau is now agent.ddpg.tau: write \+agent.ddpg.tau=0.1"):
        compose("train_agent", ["+agent.tau=0.1"])
    with pytest.raises(ValueError, match="gamma"):
        DDPGConfig(gamma=1.5)


# ------------------------------------------------------------------------------------ the learner options
def test_n_step_window_returns_match_hand_computation():
    from worldmodel.models.ddpg import NStepWindow

    g = 0.5
    w = NStepWindow(3, g)
    o = [np.full(2, float(i)) for i in range(6)]  # o[t] is the observation at step t
    out = []
    out += w.push(o[0], "a0", 1.0, o[1], False)
    out += w.push(o[1], "a1", 2.0, o[2], False)
    assert out == []  # nothing is complete before n steps
    out += w.push(o[2], "a2", 4.0, o[3], False)
    out += w.push(o[3], "a3", 8.0, o[4], True)  # a termination flushes the rest, each as long as remains
    assert [t[1] for t in out] == ["a0", "a1", "a2", "a3"]
    # (return, next obs index, terminated, steps)
    expected = [(1 + 0.5 * 2 + 0.25 * 4, 3, False, 3), (2 + 0.5 * 4 + 0.25 * 8, 4, True, 3), (4 + 0.5 * 8, 4, True, 2)]
    expected.append((8.0, 4, True, 1))
    for (_, _, ret, nxt, term, k), (e_ret, e_next, e_term, e_k) in zip(out, expected):
        assert ret == pytest.approx(e_ret) and nxt[0] == e_next and term == e_term and k == e_k
    # a truncated episode: flush bootstraps every pending transition from the last observation
    w.push(o[0], "b0", 1.0, o[1], False)
    w.push(o[1], "b1", 1.0, o[2], False)
    tail = w.flush()
    assert [(t[2], t[3][0], t[4], t[5]) for t in tail] == [(1.5, 2.0, False, 2), (1.0, 2.0, False, 1)]


def test_n_step_target_discounts_by_gamma_to_the_k():
    cfg = DDPGConfig(**SMALL, gamma=0.9)
    agent = DDPG(3, 1, cfg, seed=0)
    batch = {
        "obs": torch.zeros(2, 3),
        "actions": torch.zeros(2, 1),
        "rewards": torch.tensor([1.0, -2.0]),
        "next_obs": torch.ones(2, 3),
        "terminated": torch.tensor([0.0, 0.0]),
        "steps": torch.tensor([3.0, 1.0]),
    }
    with torch.no_grad():
        q_next = agent.critic_target(batch["next_obs"], agent.actor_target(batch["next_obs"]))
    expected = batch["rewards"] + torch.tensor([0.9**3, 0.9]) * q_next
    torch.testing.assert_close(agent.td_target(batch), expected)


def test_twin_critic_target_takes_the_smaller_target_q():
    agent = make_agent(3, 1, DDPGConfig(**SMALL, twin_critics=True), seed=0)
    assert isinstance(agent, TD3)
    with torch.no_grad():  # make the two target critics disagree by a known amount
        agent.critic2_target.net[-1].bias += 5.0
    batch = {
        "obs": torch.zeros(4, 3),
        "actions": torch.zeros(4, 1),
        "rewards": torch.zeros(4),
        "next_obs": torch.randn(4, 3),
        "terminated": torch.zeros(4),
    }
    with torch.no_grad():
        a = agent.actor_target(batch["next_obs"])
        q1 = agent.critic_target(batch["next_obs"], a)
        q2 = agent.critic2_target(batch["next_obs"], a)
    assert torch.all(q2 > q1)
    torch.testing.assert_close(agent.td_target(batch), agent.cfg.gamma * torch.minimum(q1, q2))


def test_q_filter_clones_only_where_the_critic_prefers_the_demonstration():
    agent = DDPG(2, 1, DDPGConfig(**SMALL, bc_weight=1.0, q_filter=True), seed=0)
    # a critic with a known shape: Q(s, a) = a (the bigger the action, the better)
    critic = agent.critic
    with torch.no_grad():
        for p in critic.parameters():
            p.zero_()
    critic.forward = lambda obs, action: action[:, 0]
    obs = torch.zeros(4, 2)
    batch = {
        "obs": obs,
        "actions": torch.tensor([[0.5], [-0.5], [0.9], [0.0]]),
        "demo": torch.tensor([1.0, 1.0, 1.0, 0.0]),  # the last sample is the agent's own
    }
    policy = torch.tensor([[0.2], [0.2], [0.2], [0.2]])
    loss, kept = agent.bc_loss(batch, policy, critic(obs, policy))
    # kept: demos 0 (0.5 > 0.2) and 2 (0.9 > 0.2); not 1 (-0.5 < 0.2); the non-demo never counts
    assert kept == pytest.approx(2 / 3)
    assert loss.item() == pytest.approx(((0.2 - 0.5) ** 2 + (0.2 - 0.9) ** 2) / 3)
    agent.cfg.q_filter = False
    loss, kept = agent.bc_loss(batch, policy, critic(obs, policy))
    assert kept == 1.0 and loss.item() == pytest.approx((0.09 + 0.49 + 0.49) / 3)


def test_critic_with_the_action_at_its_second_layer_uses_the_action():
    critic = Critic(5, 2, (16, 8), action_layer=1)
    assert critic.first[0].in_features == 5 and critic.net[0].in_features == 16 + 2
    obs = torch.randn(3, 5)
    a, b = torch.zeros(3, 2), torch.ones(3, 2)
    torch.nn.init.normal_(critic.net[-1].weight)
    assert not torch.allclose(critic(obs, a), critic(obs, b))


def test_default_learner_is_unchanged_by_the_new_options():
    """All options off: the same networks, from the same seed, as before they existed (no second critic drawn)."""
    agent = make_agent(4, 2, DDPGConfig(**SMALL), seed=3)
    assert type(agent) is DDPG and not hasattr(agent, "critic2")
    assert isinstance(agent.critic.net[0], torch.nn.Linear) and agent.critic.net[0].in_features == 6


def test_ddpg_refuses_the_options_of_td3():
    with pytest.raises(ValueError, match="agent.ddpg.policy_delay, agent.ddpg.target_noise: TD3's options"):
        DDPG(4, 2, DDPGConfig(**SMALL, policy_delay=2, target_noise=0.1), seed=3)


def test_td3_with_its_options_off_learns_exactly_as_ddpg():
    """TD3 is DDPG plus its options: built with none of them on, it draws and learns the same bits."""
    plain, td3 = DDPG(4, 2, DDPGConfig(**SMALL), seed=3), TD3(4, 2, DDPGConfig(**SMALL), seed=3)
    rng = np.random.default_rng(0)
    batch = {
        "obs": torch.randn(8, 4, generator=torch.Generator().manual_seed(1)),
        "actions": torch.as_tensor(rng.uniform(-1, 1, (8, 2)), dtype=torch.float32),
        "rewards": torch.as_tensor(rng.normal(size=8), dtype=torch.float32),
        "next_obs": torch.randn(8, 4, generator=torch.Generator().manual_seed(2)),
        "terminated": torch.zeros(8),
    }
    for _ in range(3):
        assert plain.update(batch) == td3.update(batch)
    for p, q in zip(plain.actor.parameters(), td3.actor.parameters(), strict=True):
        assert torch.equal(p, q)


def test_cloning_fits_a_known_state_to_action_map():
    torch.manual_seed(0)
    agent = DDPG(4, 2, DDPGConfig(**SMALL, actor_final_bound=0.0), seed=0)
    obs = torch.randn(512, 4)
    target = torch.tanh(obs[:, :2] - 0.5 * obs[:, 2:])  # reachable by the tanh actor
    before = ((agent.actor(obs) - target) ** 2).sum(-1).mean().item()
    for _ in range(600):
        idx = torch.randint(0, 512, (64,))
        agent.clone(obs[idx], target[idx])
    with torch.no_grad():
        after = ((agent.actor(obs) - target) ** 2).sum(-1).mean().item()
    assert after < 0.05 * before


def test_weighted_cloning_fits_the_weighted_samples():
    """agent.kim.bc_steer_weight's loss: a sample of weight 0 does not pull the actor, so a step on (a, b) weighted
    (1, 0) is a step on a alone; equal weights are the plain mean."""
    obs, target = torch.randn(2, 4), torch.tensor([[0.5, -0.5], [-0.9, 0.9]])
    twins = [DDPG(4, 2, DDPGConfig(**SMALL), seed=1) for _ in range(4)]
    twins[0].clone(obs, target, torch.tensor([1.0, 0.0]))
    twins[1].clone(obs[:1], target[:1])
    twins[2].clone(obs, target, torch.tensor([3.0, 3.0]))
    twins[3].clone(obs, target)
    for a, b in ((0, 1), (2, 3)):
        for p, q in zip(twins[a].actor.parameters(), twins[b].actor.parameters(), strict=True):
            torch.testing.assert_close(p, q)
    moved = [
        not torch.equal(p, q) for p, q in zip(twins[0].actor.parameters(), twins[2].actor.parameters(), strict=True)
    ]
    assert any(moved)


def test_lidar_front_end_reads_scans_through_circular_convolutions():
    """Kim et al.'s encoder: 4 scans x 36 rays -> 32 x 17 features, plus the observation's other numbers untouched.
    The angle wraps: an obstacle on the last ray reaches the first output position, as one on the second ray does."""
    from worldmodel.models.ddpg import LidarEncoder

    torch.manual_seed(0)
    enc = LidarEncoder(4 * 36 + 2, 4, 36)
    obs = torch.ones(3, 4 * 36 + 2)
    obs[:, -2:] = torch.tensor([0.25, -0.5])
    out = enc(obs)
    assert out.shape == (3, 32 * 17 + 2) and enc.out_dim == 32 * 17 + 2
    assert torch.equal(out[:, -2:], obs[:, -2:])
    first = enc.conv[0]
    base = first(torch.ones(1, 4, 36))
    for ray in (1, 35):
        poked = torch.ones(1, 4, 36)
        poked[0, :, ray] = 0.0
        assert not torch.allclose(first(poked)[0, :, 0], base[0, :, 0]), ray
    cfg = DDPGConfig(lidar_scans=4, actor_hidden=[16], critic_hidden=[16])
    agent = DDPG(4 * 36 + 2, 2, cfg, seed=0)
    assert agent.act(np.ones((5, 146), np.float32), explore=False).shape == (5, 2)
    with pytest.raises(ValueError, match="lidar_scans"):
        DDPGConfig(lidar_scans=-1)


def test_sampling_without_replacement_draws_each_transition_once():
    """The trauma memory's draw (``replace=False``): a sample the size of the store is a permutation of it; an empty
    store says what it is."""
    buffer = ReplayBuffer(8, obs_dim=1, act_dim=1)
    for i in range(5):
        buffer.add(np.array([float(i)]), np.zeros(1), 0.0, np.zeros(1), False)
    rng = np.random.default_rng(0)
    for _ in range(20):
        drawn = buffer.sample(5, rng, replace=False)["obs"][:, 0].tolist()
        assert sorted(drawn) == [0.0, 1.0, 2.0, 3.0, 4.0]
    with pytest.raises(ValueError, match="cannot sample from an empty replay buffer"):
        ReplayBuffer(4, obs_dim=1, act_dim=1).sample(2, rng)
