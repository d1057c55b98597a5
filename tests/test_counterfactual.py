"""The counterfactual-cost actor (``envs/counterfactual.py``, ``worldmodel/counterfactual.py``): shifts, their labels
by re-simulation, and the critic fitted to them. Checked on the real scene and the real smoke-scale world model: a
label is exactly what driving the shift costs, a second decision never makes a label dearer, and the fitted critic
orders held-out shifts better than a constant does. Its exact resume is in test_resume.py; the smoke pipeline trains
and evaluates it (test_pipeline.py)."""

from __future__ import annotations

import numpy as np
import pytest

from envs import UrbanCollisionEnv, sample_focus_scenario
from envs.counterfactual import BRAKE, Shift, ShiftPolicy, ShiftSpace, label_episode, shift_cost
from worldmodel import counterfactual, counterfactual_labels, loading
from worldmodel.config import CounterfactualConfig, validate
from worldmodel.models import counterfactual as counterfactual_models

CONTINUATIONS = CounterfactualConfig().continuations(1.0 / 15.0)


def scenarios(n: int, seed: int = 5):
    rng = np.random.default_rng(seed)
    return [sample_focus_scenario(rng, 1.0, (20.0, 30.0), (0.4, 1.0)) for _ in range(n)]


def test_a_shift_steers_counter_steers_then_brakes_and_zero_is_braking():
    space = ShiftSpace((0.15, 0.6))
    braking = space.shift([0.0, 0.0, 0.3])
    assert all((braking.action(k) == BRAKE).all() for k in range(30))
    shift = space.shift([0.5, 0.5, 1.0])  # pedal 0: coast; the longest hold, 0.6 s = 9 steps
    assert (shift.pedal, shift.hold) == (0.0, 9)
    np.testing.assert_array_equal(shift.action(0), [0.5, 0.0])
    np.testing.assert_array_equal(shift.action(9), [-0.5, 0.0])
    np.testing.assert_array_equal(shift.action(18), BRAKE)
    assert space.shift([0.0, 0.0, -1.0]).hold == 2  # 0.15 s
    with pytest.raises(ValueError, match="hold_s"):
        ShiftSpace((0.6, 0.15))


def test_a_label_is_what_driving_the_shift_costs_and_a_second_decision_never_adds():
    """A policy that brakes, then shifts at its last decision: the label of its choice there equals the R2 cost the
    live episode accrues from that step on; at its first decision, each label is at most the shift run on alone."""
    env = UrbanCollisionEnv(camera=False)
    twin = env.planning_twin()
    space = ShiftSpace()
    choice = np.array([0.7, 0.3, -0.2], np.float32)
    costly = 0
    for spec in scenarios(6):
        policy = ShiftPolicy(space, lambda x, d: choice if d == 1 else np.zeros(3, np.float32), 2, 5)
        proposals = lambda d, chosen: np.stack([chosen, [-0.6, 0.0, 0.5], [0.2, 1.0, 0.0]])  # noqa: E731
        lab = label_episode(env, spec, policy, proposals, CONTINUATIONS, twin)
        if len(lab["t"]) < 2:
            continue
        env.reset(options={"scenario": spec})
        policy.reset()
        obs, live, t, done = None, 0.0, 0, False
        while not done:
            _, _, terminated, truncated, info = env.step(policy.act(obs, None))
            live -= info["reward_r2"] if t >= lab["t"][1] else 0.0
            t, done = t + 1, terminated or truncated
        assert lab["costs"][1, 0] == pytest.approx(live, abs=1e-6)
        costly += live > 0
        env.reset(options={"scenario": spec})
        snap = env.snapshot()
        for u, label in zip(lab["u"][0], lab["costs"][0]):
            run_on, _ = shift_cost(twin, snap, space.shift(u), None)
            assert label <= run_on + 1e-6
    assert costly, "no scenario here costs anything after the last decision: the check would be empty"


def test_shift_cost_prefers_a_cheaper_continuation():
    """Hard right at 30 m/s ends against the kerb side; a second decision that shifts back left or brakes straight
    may cost less, and the label is the cheapest of them and of running on."""
    env = UrbanCollisionEnv(camera=False)
    twin = env.planning_twin()
    found = False
    for spec in scenarios(10, seed=11):
        env.reset(options={"scenario": spec})
        snap = env.snapshot()
        shift = Shift(1.0, -1.0, 9)
        run_on, _ = shift_cost(twin, snap, shift, None)
        with_second, _ = shift_cost(twin, snap, shift, 5, CONTINUATIONS)
        each = []
        for other in CONTINUATIONS:  # by hand: the shift for 5 steps, then the other from there
            twin.restore(snap)
            cost = 0.0
            for k in range(5):
                _, _, term, trunc, info = twin.step(shift.action(k))
                cost -= info["reward_r2"]
                if term or trunc:
                    break
            else:
                for k in range(10_000):
                    _, _, term, trunc, info = twin.step(other.action(k))
                    cost -= info["reward_r2"]
                    if term or trunc:
                        break
            each.append(cost)
        assert with_second == pytest.approx(min([run_on, *each]), abs=1e-6)
        found |= with_second < run_on - 1e-3
    assert found, "no scenario here where a second decision helps: the check would be empty"


@pytest.fixture(scope="module")
def labelled(smoke_builds):
    """Round 0's labels of 16 braking episodes on the smoke world model, with 6 shifts per decision."""
    from worldmodel.config import compose

    root = smoke_builds("rnn")
    overrides = [
        *(f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"),
        *("threads=1", "reward=r2", "agent=counterfactual", "agent.counterfactual.episodes=16"),
        "agent.counterfactual.proposals=6",
    ]
    cfg = compose("train_agent", overrides)
    c = validate(cfg).agent.counterfactual
    directory = counterfactual_labels.labels_dir(cfg, 0)
    data = counterfactual_labels.labels(cfg, 0, c.episodes, directory)
    encoder = loading.load_world_model(cfg)
    data["x"] = counterfactual_labels.encode_states(encoder, data, c.decisions)
    return cfg, c, data


def test_the_fitted_critic_orders_held_out_shifts_better_than_a_constant(labelled):
    cfg, c, data = labelled
    held = counterfactual_labels.held_out_rows(data["episode"])
    assert 0 < held.sum() < len(held)
    assert counterfactual.pairwise_order(np.zeros_like(data["costs"][held]), data["costs"][held]) == 0.5
    fit = CounterfactualConfig(**{**vars(c), "critic_steps": 400, "batch_size": 64})
    critic, figures = counterfactual.fit_critic(
        data["x"], data["u"], data["costs"], data["state"], held, fit, seed=0, round_=0
    )
    assert figures["pairwise_order"] > 0.6, figures
    # and the actor it trains, which starts as braking, ends with a lower objective on the held-out states
    actor = counterfactual_models.ShiftActor(data["x"].shape[1], (64, 64))
    figures = counterfactual.fit_actor(actor, critic, data["x"], data["x"], data["state"], held, fit, seed=0, round_=0)
    assert figures["objective"] < figures["braking_objective"], figures


def test_search_picks_shifts_no_worse_than_the_actors_or_braking_and_a_true_state_critic_trains_the_actor(labelled):
    """``search``: per state, the target is the candidate of lowest objective, never worse than the actor's own shift
    or braking; ``critic_obs=privileged``: a critic on the true state trains the actor that reads the world model."""
    import torch

    cfg, c, data = labelled
    held = counterfactual_labels.held_out_rows(data["episode"])
    true_state = counterfactual_labels.privileged_states(data, c.decisions)
    fit = CounterfactualConfig(**{**vars(c), "critic_steps": 300, "actor_steps": 150, "batch_size": 64, "search": 16})
    critic, _ = counterfactual.fit_critic(true_state, data["u"], data["costs"], data["state"], held, fit, 0, 0)
    xc = torch.from_numpy(true_state)
    u = torch.rand(len(xc), 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    target = counterfactual.searched_shifts(critic, u, xc, fit, torch.Generator().manual_seed(1))
    with torch.no_grad():
        own, scale = counterfactual.objective(critic, u, xc, fit)
        found = counterfactual.objective(critic, target, xc, fit, scale)[0]
        braking = counterfactual.objective(critic, torch.zeros_like(u), xc, fit, scale)[0]
    assert (found <= own + 1e-6).all() and (found <= braking + 1e-6).all()
    assert (found < own - 1e-6).any(), "the search never improved on a random shift: the check would be empty"
    actor = counterfactual_models.ShiftActor(data["x"].shape[1], (64, 64))
    figures = counterfactual.fit_actor(actor, critic, data["x"], true_state, data["state"], held, fit, seed=0, round_=0)
    assert figures["objective"] < figures["braking_objective"], figures


def test_on_the_true_state_it_trains_and_acts_without_world_model_or_camera(experiment_copy, stage_cfg):
    """``obs=privileged``: the labels' recorded true state is the critic's and the actor's input, the DAgger round
    drives with it, and evaluation runs the actor on the bound env's true state with the camera off."""
    import torch
    from omegaconf import OmegaConf

    from envs.privileged import PRIVILEGED_DIM, privileged_state
    from worldmodel import policies, train_agent
    from worldmodel.families.porav import evaluation as porav_eval

    root = experiment_copy("rnn")
    overrides = ("reward=r2", "agent=counterfactual", "obs=privileged", "agent.use_speed=false")
    out = train_agent.run(stage_cfg("train_agent", *overrides, root=root))
    assert set(out["history"]) == {"critic0", "actor0", "critic1", "actor1"}
    cfg = stage_cfg("evaluate", root=root)
    key = "agent_r2_counterfactual-privileged/seed0"
    state = torch.load(root / "runs/t" / key / "last.pt", weights_only=False)
    assert state["obs"] == "privileged" and state["in_dim"] == PRIVILEGED_DIM + 1
    policy, _, models = policies.policy_for(cfg, key)
    assert policy.needs_camera is False and models["vae_sha"] == "" and models["rnn_sha"] == ""
    env, built, _, _ = porav_eval._build(OmegaConf.to_container(cfg, resolve=True), key)
    assert env._camera is None  # the camera is off
    spec = scenarios(1)[0]
    env.reset(options={"scenario": spec})
    built.reset()
    built.bind(env)
    expected = counterfactual_labels.actor_decision(counterfactual_models.actor_from_state(state), state["decisions"])(
        privileged_state(env), 0
    )
    built.act({"seg": None}, None)
    np.testing.assert_allclose(built.chosen[0], expected, atol=1e-6)
    env.close()


def test_the_label_curves_figures_by_hand():
    """``experiments/critic_label_curve.py``: a perfect critic captures all of braking's excess over the cheapest
    labelled shift, a constant one none (it never switches), a reversed one loses to braking; a margin larger than
    every predicted saving keeps braking."""
    from experiments import critic_label_curve as clc

    u = np.zeros((3, 3, 3), np.float32)  # shift 0 is braking
    u[:, 1, 0], u[:, 2, 0] = 0.5, -0.5
    costs = np.array([[0.3, 0.1, 0.2], [0.2, 0.2, 0.0], [0.1, 0.4, 0.3]])
    episode = np.arange(3)
    perfect = clc.summarise(costs, u, costs, episode, 0.0, boot=200)
    assert perfect["captured"] == pytest.approx(100.0) and perfect["switches"] == pytest.approx(200 / 3)
    assert perfect["low"] == pytest.approx(100.0) and perfect["high"] == pytest.approx(100.0)
    constant = clc.summarise(np.ones_like(costs), u, costs, episode, 0.0, boot=0)
    assert constant["captured"] == 0.0 and constant["switches"] == 0.0
    reverse = clc.summarise(-costs, u, costs, episode, 0.0, boot=0)  # picks 0.3 (braking), 0.2 (braking), 0.4
    assert reverse["captured"] == pytest.approx(100 * (0.2 - 0.3) / (0.2 - 0.2 / 3))
    assert clc.summarise(costs, u, costs, episode, 0.25, boot=0)["captured"] == 0.0


def test_the_true_state_preset_is_named_by_its_preset_and_its_rows_name_no_world_model(stage_cfg, experiment_copy):
    """agent=counterfactual_true_state reads the true state as its own input: its run has no -privileged suffix, and
    the models behind its evaluation rows are its actor alone, though the experiment has a world model."""
    from worldmodel import train_agent
    from worldmodel.artifacts import AgentId

    root = experiment_copy("rnn")
    cfg = stage_cfg("train_agent", "agent=counterfactual_true_state", "reward=r2", root=root)
    train_agent.run(cfg)
    agent = AgentId.of(cfg)
    assert agent == AgentId("r2", 0, "counterfactual_true_state") and agent.dir(cfg).name == "seed0"
    assert agent.dir(cfg).parent.name == "agent_r2_counterfactual_true_state"
    models = loading.models_of(cfg, agent)
    assert models["vae_sha"] == models["rnn_sha"] == "" and len(models["actor_sha"]) == 12
