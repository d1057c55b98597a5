"""DQN and Double DQN with Chae's trauma memory: targets follow the equations on hand-set weights, the trauma memory
joins every batch, schedules and target copies happen when they should, checkpoints resume exactly, and both
variants learn a small corridor. Real networks and optimisers; the file runs in seconds on one thread."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from worldmodel.common import ConfigValueError
from worldmodel.models.dqn import DQN, DQNConfig, QNetwork, TransitionBuffer, squash, unsquash

torch.set_num_threads(1)


def roundtrip(obj):
    """Through bytes, as a checkpoint file would, so nothing aliases the original's tensors or arrays."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=False)


def params(net: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in net.parameters()]


def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


# ----------------------------------------------------------------------------- TD targets
def set_weights(net: QNetwork, w1, b1, w2, b2) -> None:
    first, last = net.net[0], net.net[2]
    with torch.no_grad():
        first.weight.copy_(torch.tensor(w1, dtype=torch.float32))
        first.bias.copy_(torch.tensor(b1, dtype=torch.float32))
        last.weight.copy_(torch.tensor(w2, dtype=torch.float32))
        last.bias.copy_(torch.tensor(b2, dtype=torch.float32))


@pytest.mark.parametrize("double, expected_first", [(False, 0.5 + 0.9 * 2.5), (True, 0.5 + 0.9 * 1.0)])
def test_td_targets_match_hand_computation(double, expected_first):
    """s' = (1, 2), hidden layer of 2 with leaky slope 0.01.
    Target net: h = leaky(1, -2) = (1, -0.02), Q' = (1, -100 * -0.02 + 0.5) = (1, 2.5): argmax 1.
    Online net: h = (1, 2), Q = (1, 0): argmax 0.
    DQN takes max Q' = 2.5; Double DQN takes Q'(s', argmax Q) = Q'(s', 0) = 1. A terminal transition is just r."""
    cfg = DQNConfig(hidden=[2], leaky_slope=0.01, gamma=0.9, double=double, batch_size=2, buffer_size=2)
    agent = DQN(obs_dim=2, n_actions=2, cfg=cfg, seed=0)
    set_weights(agent.target_network, [[1, 0], [0, -1]], [0, 0], [[1, 0], [0, -100]], [0, 0.5])
    set_weights(agent.q_network, [[1, 0], [0, 1]], [0, 0], [[1, 0], [0, 0]], [0, 0])
    next_obs = torch.tensor([[1.0, 2.0], [1.0, 2.0]])
    with torch.no_grad():
        assert agent.target_network(next_obs)[0].tolist() == pytest.approx([1.0, 2.5])
        assert agent.q_network(next_obs)[0].tolist() == pytest.approx([1.0, 0.0])

    y = agent.td_targets(torch.tensor([0.5, -1.0]), next_obs, torch.tensor([0.0, 1.0]))
    assert y.tolist() == pytest.approx([expected_first, -1.0], abs=1e-6)


def h_inverse_by_bisection(y: float) -> float:
    """Solves sign(x) (sqrt(|x| + 1) - 1) + 0.001 x = y without the closed form the code uses."""
    lo, hi = -1e6, 1e6
    for _ in range(200):
        mid = (lo + hi) / 2
        h = np.sign(mid) * (np.sqrt(abs(mid) + 1) - 1) + 1e-3 * mid
        lo, hi = (mid, hi) if h < y else (lo, mid)
    return (lo + hi) / 2


def test_value_rescaling_takes_the_bellman_step_in_returns_and_squashes_it():
    """The same nets, now holding h(Q). DQN: a' = argmax Q'(s', .) = 1 (h is increasing), its return is
    h^-1(2.5) ~ 11.2, so y = h(0.5 + 0.9 h^-1(2.5)); a terminal transition is h(r). A collision's -100 is stored
    as -(sqrt(101) - 1) - 0.1, and q_values answers in returns."""
    cfg = DQNConfig(hidden=[2], leaky_slope=0.01, gamma=0.9, value_rescale=True, batch_size=2, buffer_size=2)
    agent = DQN(obs_dim=2, n_actions=2, cfg=cfg, seed=0)
    set_weights(agent.target_network, [[1, 0], [0, -1]], [0, 0], [[1, 0], [0, -100]], [0, 0.5])

    def h(x):
        return np.sign(x) * (np.sqrt(abs(x) + 1) - 1) + 1e-3 * x

    next_obs = torch.tensor([[1.0, 2.0], [1.0, 2.0]])
    y = agent.td_targets(torch.tensor([0.5, -1.0]), next_obs, torch.tensor([0.0, 1.0]))
    assert y.tolist() == pytest.approx([h(0.5 + 0.9 * h_inverse_by_bisection(2.5)), h(-1.0)], abs=1e-5)
    assert squash(torch.tensor(-100.0)).item() == pytest.approx(-(101**0.5 - 1) - 0.1, abs=1e-5)
    returns = torch.tensor([-103.0, -0.3, 0.0, 0.3, 40.0])
    assert unsquash(squash(returns)).tolist() == pytest.approx(returns.tolist(), abs=1e-3)
    set_weights(agent.q_network, [[1, 0], [0, -1]], [0, 0], [[1, 0], [0, -100]], [0, 0.5])
    q = agent.q_values(np.array([1.0, 2.0], np.float32))
    assert q.tolist() == pytest.approx([h_inverse_by_bisection(1.0), h_inverse_by_bisection(2.5)], abs=1e-4)


# ----------------------------------------------------------------------------- trauma memory
TRAUMA_CFG = dict(
    hidden=[8], batch_size=4, buffer_size=8, trauma_size=5, trauma_batch=3, warmup_steps=0, grad_clip=None, gamma=0.9
)


def agent_with_old_trauma(trauma_reward: float, **overrides) -> tuple[DQN, np.ndarray]:
    """One trauma transition, then as many ordinary ones as the replay memory holds: the trauma transition has been
    overwritten in replay, so any batch that contains it drew it from the trauma memory."""
    agent = DQN(obs_dim=3, n_actions=2, cfg=DQNConfig(**{**TRAUMA_CFG, **overrides}), seed=0)
    crash_obs = np.array([1.0, -1.0, 0.5], np.float32)
    agent.remember(crash_obs, 1, trauma_reward, np.zeros(3), terminated=True, trauma=True)
    env = np.random.default_rng(1)
    for _ in range(agent.cfg.buffer_size):
        agent.remember(env.normal(size=3), int(env.integers(2)), env.normal(), env.normal(size=3), False, trauma=False)
    return agent, crash_obs


def test_trauma_transition_joins_every_batch_and_drives_the_loss():
    a, crash_obs = agent_with_old_trauma(-1.0)
    b, _ = agent_with_old_trauma(-10.0)
    assert len(a.trauma) == 1 and -1.0 not in a.replay.rewards  # stored once in trauma, gone from replay
    q = a.q_values(crash_obs)[1]
    assert b.q_values(crash_obs)[1] == q

    # Same seed, same replay batch: the two losses differ only by the trauma term (sum loss, terminal: y = r).
    loss_a, loss_b = a.update()["loss"], b.update()["loss"]
    assert loss_a - loss_b == pytest.approx((q + 1.0) ** 2 - (q + 10.0) ** 2, rel=1e-4)

    for _ in range(20):
        assert a.update()["trauma_in_batch"] == 1.0
    for _ in range(4):  # now 5 stored, 3 drawn per batch
        a.remember(np.ones(3), 0, -1.0, np.zeros(3), terminated=True, trauma=True)
    assert len(a.trauma) == 5
    assert a.update()["trauma_in_batch"] == 3.0


def test_mean_losses_divide_by_the_whole_batch():
    """With loss=mse the trauma term is averaged over replay + trauma batch (4 + 1 transitions)."""
    a, crash_obs = agent_with_old_trauma(-1.0, loss="mse")
    b, _ = agent_with_old_trauma(-10.0, loss="mse")
    q = a.q_values(crash_obs)[1]
    assert a.update()["loss"] - b.update()["loss"] == pytest.approx(((q + 1.0) ** 2 - (q + 10.0) ** 2) / 5, rel=1e-4)


def test_empty_or_disabled_trauma_memory_adds_nothing():
    env = np.random.default_rng(0)
    on = DQN(3, 2, DQNConfig(**TRAUMA_CFG), seed=0)
    off = DQN(3, 2, DQNConfig(**{**TRAUMA_CFG, "trauma_batch": 0}), seed=0)
    for _ in range(10):
        transition = (env.normal(size=3), int(env.integers(2)), env.normal(), env.normal(size=3), False)
        on.remember(*transition, trauma=False)
        off.remember(*transition, trauma=True)
    assert len(on.trauma) == 0 and on.update()["trauma_in_batch"] == 0.0
    assert off.trauma is None and off.state_dict()["trauma"] is None
    assert off.update()["trauma_in_batch"] == 0.0


# ----------------------------------------------------------------------------- ring buffer
def test_ring_buffer_overwrites_the_oldest_and_samples_reproducibly():
    buf = TransitionBuffer(3, obs_dim=2)
    for i in range(5):
        buf.add([i, -i], i, float(i), [i + 1, -i - 1], terminated=i % 2 == 1)
    assert len(buf) == 3
    assert buf.rewards.tolist() == [3.0, 4.0, 2.0]  # 0 and 1 overwritten, in slot order
    assert buf.actions.dtype == np.int64

    batch = buf.sample(50, np.random.default_rng(7))
    assert batch["actions"].dtype == torch.int64
    assert set(batch["actions"].tolist()) == {2, 3, 4}
    # each row is one whole transition
    assert torch.equal(batch["obs"][:, 0], batch["rewards"])
    assert torch.equal(batch["next_obs"][:, 0], batch["rewards"] + 1)
    assert torch.equal(batch["terminated"], (batch["actions"] % 2).float())

    again = buf.sample(50, np.random.default_rng(7))
    assert all(torch.equal(batch[k], again[k]) for k in batch)
    other = buf.sample(50, np.random.default_rng(8))
    assert not torch.equal(batch["actions"], other["actions"])

    restored = TransitionBuffer(3, obs_dim=2)
    restored.load_state_dict(roundtrip(buf.state_dict()))
    restored.add([9, 9], 9, 9.0, [9, 9], False)  # the restored one also overwrites the oldest (reward 2) next
    assert restored.rewards.tolist() == [3.0, 4.0, 9.0]


# ----------------------------------------------------------------------------- schedules and target copies
def test_epsilon_schedule_and_greedy_acting():
    agent = DQN(4, 3, DQNConfig(hidden=[8], eps_start=1.0, eps_end=0.1, eps_decay_steps=100), seed=0)
    assert agent.epsilon(0) == 1.0
    assert agent.epsilon(50) == pytest.approx(0.55)
    assert agent.epsilon(100) == pytest.approx(0.1)
    assert agent.epsilon(10_000) == pytest.approx(0.1)
    assert agent.epsilon() == agent.epsilon(0)  # default clock: transitions remembered

    obs = np.random.default_rng(0).normal(size=(40, 4)).astype(np.float32)
    greedy = agent.q_values(obs).argmax(1)
    assert [agent.act(o, explore=False) for o in obs] == greedy.tolist()
    random_actions = [agent.act(obs[0], step=0) for _ in range(60)]  # epsilon 1: uniform
    assert set(random_actions) == {0, 1, 2}


def test_learning_rate_decays_exponentially_to_lr_final():
    cfg = DQNConfig(hidden=[4], lr=1e-2, lr_final=1e-4, total_steps=10, batch_size=2, buffer_size=4, warmup_steps=0)
    agent = DQN(2, 2, cfg, seed=0)
    for _ in range(4):
        agent.remember(np.ones(2), 0, 1.0, np.ones(2), True)
    lrs = [agent.update()["lr"] for _ in range(13)]
    assert lrs[0] == pytest.approx(1e-2)
    assert lrs[5] == pytest.approx(1e-3)
    assert lrs[10] == pytest.approx(1e-4)
    assert lrs[12] == pytest.approx(1e-4)  # held after total_steps


def test_target_copies_exactly_every_target_every_updates():
    cfg = DQNConfig(hidden=[8], batch_size=4, buffer_size=50, warmup_steps=10, target_every=3, trauma_batch=0)
    agent = DQN(3, 2, cfg, seed=0)
    env = np.random.default_rng(0)
    for _ in range(9):
        agent.remember(env.normal(size=3), int(env.integers(2)), env.normal(), env.normal(size=3), False)
        assert agent.update() is None  # warming up
    agent.remember(env.normal(size=3), 0, 1.0, env.normal(size=3), True)

    last_copy = params(agent.q_network)
    assert same(params(agent.target_network), last_copy)  # starts as a copy
    for k in range(1, 8):
        assert agent.update() is not None
        online, target = params(agent.q_network), params(agent.target_network)
        if k % 3 == 0:
            assert same(target, online)
            last_copy = online
        else:
            assert not same(target, online)
            assert same(target, last_copy)


# ----------------------------------------------------------------------------- checkpoints
def run(agent: DQN, start: int, stop: int, env: dict) -> list[dict | None]:
    """Steps start..stop of a fixed random 'environment'; acting, replay and updates all use the agent's rng."""
    infos = []
    for t in range(start, stop):
        action = agent.act(env["obs"][t], t)
        crash = t % 7 == 6
        agent.remember(env["obs"][t], action, env["reward"][t, action], env["obs"][t + 1], crash, trauma=crash)
        infos.append(agent.update())
    return infos


def test_resume_continues_exactly():
    cfg = DQNConfig(
        hidden=[16, 16],
        optimizer="adam",
        lr=1e-3,
        lr_final=1e-5,
        total_steps=50,
        batch_size=8,
        buffer_size=30,  # wraps around before and after the save
        trauma_size=4,
        trauma_batch=2,
        target_every=7,
        double=True,
        eps_decay_steps=60,
        warmup_steps=10,
    )
    gen = np.random.default_rng(3)
    env = {"obs": gen.normal(size=(81, 5)).astype(np.float32), "reward": gen.normal(size=(80, 3))}

    straight = DQN(5, 3, cfg, seed=0)
    run(straight, 0, 80, env)

    first = DQN(5, 3, cfg, seed=0)
    run(first, 0, 45, env)
    checkpoint = roundtrip(first.state_dict())
    resumed = DQN(5, 3, cfg, seed=123)  # a different seed: everything that matters must come from the checkpoint
    resumed.load_state_dict(checkpoint)
    run(resumed, 45, 80, env)

    assert same(params(resumed.q_network), params(straight.q_network))
    assert same(params(resumed.target_network), params(straight.target_network))
    assert resumed.updates == straight.updates == 71  # from step 9, when 10 transitions are in
    assert resumed.optimizer.param_groups[0]["lr"] == straight.optimizer.param_groups[0]["lr"]
    assert resumed.rng.random() == straight.rng.random()


# ----------------------------------------------------------------------------- learning a known answer
CORRECT = (1, 0, 1)  # the action that moves on in each corridor cell; the other one crashes


def corridor_step(state: int, action: int) -> tuple[int, float, bool]:
    """Cells 0, 1, 2. The right action moves on (reward 0), out of cell 2 with +1; the wrong one is a -1 crash."""
    if action != CORRECT[state]:
        return state, -1.0, True
    if state == len(CORRECT) - 1:
        return state, 1.0, True
    return state + 1, 0.0, False


@pytest.mark.parametrize("double", [False, True])
def test_learns_the_corridor(double):
    cfg = DQNConfig(
        hidden=[32],
        lr=1e-3,
        gamma=0.9,
        batch_size=16,
        buffer_size=1000,
        trauma_size=100,
        trauma_batch=4,
        target_every=20,
        double=double,
        eps_decay_steps=300,
        warmup_steps=50,
    )
    agent = DQN(3, 2, cfg, seed=0)
    one_hot = np.eye(3, dtype=np.float32)
    state = 0
    for step in range(500):
        action = agent.act(one_hot[state], step)
        next_state, reward, done = corridor_step(state, action)
        agent.remember(one_hot[state], action, reward, one_hot[next_state], done, trauma=reward < 0)
        agent.update()
        state = 0 if done else next_state

    q = agent.q_values(one_hot)
    assert q.argmax(1).tolist() == list(CORRECT), q
    q_right = q[np.arange(3), list(CORRECT)]
    assert q_right == pytest.approx([0.81, 0.9, 1.0], abs=0.1), q  # gamma^2, gamma, 1


# ----------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "key, value",
    [
        ("eps_start", 1.5),
        ("eps_end", -0.1),
        ("buffer_size", -5),
        ("trauma_batch", -1),
        ("optimizer", "sgd"),
        ("loss", "l1"),
        ("lr_final", 1.0),  # above lr: not a decay
        ("gamma", 1.5),
        ("target_every", 0),
        ("hidden", [100, 0]),
        ("trauma_weight_final", 0.0),  # an exponential decay cannot reach 0
        ("trauma_weight_final", 1.5),
    ],
)
def test_impossible_values_are_rejected_by_name(key, value):
    with pytest.raises(ConfigValueError) as err:
        DQNConfig(**{key: value})
    assert err.value.key == key


def test_relations_between_fields_are_checked():
    with pytest.raises(ConfigValueError) as err:
        DQNConfig(eps_start=0.1, eps_end=0.5)
    assert err.value.key == "eps_end"
    with pytest.raises(ConfigValueError) as err:
        DQNConfig(trauma_size=5, trauma_batch=10)
    assert err.value.key == "trauma_batch"
    assert DQNConfig(trauma_size=0, trauma_batch=0).trauma_batch == 0  # trauma memory off is fine


def test_trauma_weight_decays_to_its_final_value_and_scales_only_the_trauma_term():
    agent, crash_obs = agent_with_old_trauma(-1.0, loss="mse", trauma_weight_final=0.25, total_steps=4)
    assert [agent.trauma_weight(u) for u in (0, 2, 4, 9)] == pytest.approx([1.0, 0.5, 0.25, 0.25])
    for _ in range(4):
        agent.update()
    # A copy at weight 1 draws the same batch (same rng state): the losses differ by 3/4 of the trauma term, which
    # is the crash transition's squared error (terminal: y = r = -1) over the 4 + 1 transitions.
    plain = DQN(3, 2, DQNConfig(**{**agent.cfg.__dict__, "trauma_weight_final": None}), seed=0)
    plain.load_state_dict(roundtrip(agent.state_dict()))
    q_crash = agent.q_values(crash_obs)[1]
    weighted, unweighted = agent.update(), plain.update()
    assert weighted["trauma_weight"] == 0.25 and unweighted["trauma_weight"] == 1.0
    assert unweighted["loss"] - weighted["loss"] == pytest.approx(0.75 * (q_crash + 1.0) ** 2 / 5, rel=1e-4)


def test_a_checkpoint_of_a_removed_option_is_refused_by_name():
    """Weight-averaged greedy networks, averaged targets and standardised inputs are gone; a checkpoint that used one
    is refused rather than loaded without it."""
    agent = DQN(3, 2, DQNConfig(hidden=[8], trauma_batch=0), seed=0)
    state = agent.state_dict()
    for key, value in (("earlier_targets", [{}]), ("average_network", {}), ("normalized", True)):
        with pytest.raises(ValueError, match="no longer has"):
            agent.load_state_dict({**state, key: value})
    agent.load_state_dict({**state, "earlier_targets": [], "average_network": None, "normalized": False})
