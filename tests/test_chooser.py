"""The chooser (``envs/chooser.py``, ``worldmodel/chooser.py``): brake, then switch once to the manoeuvre predicted
cheapest. Checked on the real scene and the real smoke-scale world model: the exact-cost chooser is never worse
than braking, the offline cost of a labelled episode equals the simulated one, the labels are reproducible, and a
trained chooser acts in evaluation on exactly the inputs it was trained on."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from envs import StraightLineBraking, UrbanCollisionEnv, rollout, sample_focus_scenario
from envs.chooser import ExactCosts, ManoeuvreChooser, chooser_candidates, cost_labels, decide_steps_for
from envs.planner import Manoeuvre
from envs.views import CLASS_NAMES, HAZARD_CLASSES
from worldmodel import artifacts, chooser, loading, policies, train_agent
from worldmodel.common import StageError, make_env
from worldmodel.models import chooser as chooser_models

CANDIDATES = chooser_candidates(steers=(1.0,), lane_change_s=(0.3,))  # braking + 4 manoeuvres: cheap to label


def scenarios(n: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    return [sample_focus_scenario(rng, 1.0, (25.0, 30.0), (0.4, 0.9)) for _ in range(n)]


def total_risk(outcome: dict) -> float:
    return outcome["pedestrian_injury"] + outcome["occupant_injury"]


def test_candidates_start_with_braking_and_are_checked():
    assert CANDIDATES[0] == Manoeuvre(-1.0)
    assert len(chooser_candidates()) == 1 + 2 * 3 * 2  # steers x {swerve, 2 lane changes} x sides
    assert {m.delay for m in chooser_candidates()} == {0}  # waiting is deciding again at the next step
    with pytest.raises(ValueError, match="steers"):
        chooser_candidates(steers=(0.0,))
    with pytest.raises(ValueError, match="sides"):
        chooser_candidates(sides=(1.0, 1.0))
    with pytest.raises(ValueError, match="straight-line braking"):
        ManoeuvreChooser(CANDIDATES[1:], lambda o, t: np.zeros(4), 5)


def test_scripted_scores_commit_once_and_follow_the_manoeuvre():
    """A scorer that prefers candidate 2 from step 3 on: braking for 3 steps, then candidate 2's actions, open loop,
    with no further scoring; a margin above the saving keeps it braking."""
    calls = []

    def scores(obs, t):
        calls.append(t)
        return np.array([1.0, 2.0, 0.5, 2.0, 2.0]) if t >= 3 else np.array([1.0, 2.0, 2.0, 2.0, 2.0])

    policy = ManoeuvreChooser(CANDIDATES, scores, decide_steps=10)
    policy.reset()
    actions = [policy.act(None, None) for _ in range(8)]
    assert calls == [0, 1, 2, 3] and policy.choice == 2
    np.testing.assert_array_equal(actions[:3], [[0.0, -1.0]] * 3)
    np.testing.assert_array_equal(actions[3:], [CANDIDATES[2].action(k) for k in range(5)])
    cautious = ManoeuvreChooser(CANDIDATES, scores, decide_steps=10, margin=0.6)
    cautious.reset()
    assert all((cautious.act(None, None) == [0.0, -1.0]).all() for _ in range(12)) and cautious.choice is None
    # braking predicted to cost 1.0: a floor just below it lets the switch through, a floor at it keeps braking
    for floor, choice in ((0.99, 2), (1.0, None)):
        floored = ManoeuvreChooser(CANDIDATES, scores, decide_steps=10, min_brake_cost=floor)
        floored.reset()
        for _ in range(8):
            floored.act(None, None)
        assert floored.choice == choice, floor


def test_exact_costs_never_lose_to_braking_and_offline_cost_equals_the_simulated_one():
    """The exact-cost chooser's episode costs at most braking's, strictly less in some; and policy_cost on the
    labels of braking's states gives exactly the R2 cost the chooser's simulated episode returns, policy_static
    exactly whether it hit a static object (these scenarios include one where it does)."""
    env = UrbanCollisionEnv(camera=False)
    twin = env.planning_twin()
    steps = decide_steps_for(1.0)
    better, statics = 0, []
    for spec in scenarios(6):
        brake = total_risk(rollout(env, StraightLineBraking(), spec).outcome)
        policy = ManoeuvreChooser(CANDIDATES, ExactCosts(CANDIDATES), steps)
        live = rollout(env, policy, spec).outcome
        assert total_risk(live) <= brake + 1e-9
        better += total_risk(live) < brake - 1e-6
        lab = cost_labels(env, spec, CANDIDATES, steps, twin)
        offline = chooser.policy_cost(lab["costs"], lab["costs"], np.zeros(len(lab["costs"]), int), 0.0)
        assert offline[0] == pytest.approx(-live["return_r2"], abs=1e-5)
        assert lab["costs"][0, 0] == pytest.approx(brake, abs=1e-5)
        hit = chooser.policy_static(lab["costs"], lab["static"], np.zeros(len(lab["costs"]), int), 0.0)
        assert hit[0] == bool(live["static_collision"])
        assert not lab["static"][:, 0].any()  # braking straight never reaches a pole
        statics.append(hit[0])
    assert better >= 1 and any(statics) and not all(statics)


def test_hazard_state_is_where_the_scenario_put_the_hazard():
    """The privileged target of the perception head: the hazard pedestrian's centre is where the ego's bumper is
    at the TTC, walking towards the ego's lane; a scenario without hazards gives zeros."""
    from envs import ScenarioSpec
    from envs.chooser import HAZARD_STATE, hazard_state

    env = UrbanCollisionEnv(camera=False)
    spec = ScenarioSpec(seed=5, ttc=0.8, ego_speed=20.0, p_pedestrian=1.0, pedestrian_speed=3.0)
    env.reset(options={"scenario": spec})
    s = dict(zip(HAZARD_STATE, hazard_state(env)))
    assert s["pedestrian"] == 1.0 and s["car"] == 0.0
    # at the TTC the pedestrian touches the bumper: dx + vx * ttc = v_ego * ttc + L / 2 + r, within the lane
    assert s["ped_dx"] + s["ped_vx"] * 0.8 == pytest.approx(20.0 * 0.8 + env.params.length / 2 + 0.3, abs=0.01)
    assert abs(s["ped_dy"] + s["ped_vy"] * 0.8) < env.params.width / 2 and abs(s["ped_dy"]) > 1.0
    assert np.hypot(s["ped_vx"], s["ped_vy"]) == pytest.approx(3.0, abs=1e-4)
    env.reset(options={"scenario": ScenarioSpec(seed=5, ttc=0.8, ego_speed=20.0)})
    assert not hazard_state(env).any()


def test_label_seed_shares_one_label_set_between_training_seeds():
    from worldmodel.config import compose

    def cfg(*extra):
        return compose("train_agent", ["experiment=t", "scale=smoke", "agent=chooser", "reward=r2", *extra])

    own = [chooser.labels_dir(cfg(f"seed={s}")) for s in (0, 1)]
    shared = [chooser.labels_dir(cfg(f"seed={s}", "agent.chooser.label_seed=0")) for s in (0, 1)]
    assert own[0] != own[1] and shared[0] == shared[1] == own[0]
    c = chooser.cfg_chooser(cfg("seed=1", "agent.chooser.label_seed=0"))
    assert chooser.label_seed(cfg("seed=1", "agent.chooser.label_seed=0")) == 0 and c.label_seed == 0


def test_policy_cost_by_hand():
    # episode 0: the prediction first favours candidate 1 at t = 1; braking's cost falls 0.9 -> 0.8 by then
    costs = np.array([[0.9, 0.7], [0.8, 0.1], [0.8, 0.8], [0.5, 0.2]], np.float32)
    pred = np.array([[0.5, 0.6], [0.5, 0.2], [0.0, 0.0], [0.5, 0.1]], np.float32)
    episode = np.array([0, 0, 0, 1])
    np.testing.assert_allclose(chooser.policy_cost(pred, costs, episode, 0.0), [0.9 - 0.8 + 0.1, 0.2], atol=1e-6)
    # a margin of 0.35 lets only episode 1's saving (0.4) through
    np.testing.assert_allclose(chooser.policy_cost(pred, costs, episode, 0.35), [0.9, 0.2], atol=1e-6)
    # braking predicted to cost 0.5 in both: a floor of 0.5 stops both switches, 0.45 neither
    floored = chooser.policy_cost(pred, costs, episode, 0.0, min_brake_cost=0.5)
    np.testing.assert_allclose(floored, [0.9, 0.5], atol=1e-6)
    np.testing.assert_allclose(
        chooser.policy_cost(pred, costs, episode, 0.0, min_brake_cost=0.45), [0.9 - 0.8 + 0.1, 0.2], atol=1e-6
    )
    # the static flags of the chosen (row, candidate), or of braking's first row where nothing is chosen
    static = np.array([[0, 0], [0, 1], [1, 1], [0, 0]], np.int8)
    assert chooser.policy_static(pred, static, episode, 0.0).tolist() == [True, False]
    assert chooser.policy_static(pred, static, episode, 0.35).tolist() == [False, False]


def test_chunked_prediction_equals_one_forward_pass():
    torch.manual_seed(0)
    scorer = chooser_models.Scorer(12 + 2 * 8 * 8, 3, hidden=(16,), members=2, mask_shape=(2, 8, 8)).eval()
    x = torch.randn(50, 12 + 2 * 8 * 8)
    with torch.no_grad():
        whole = scorer(x).numpy()
    np.testing.assert_allclose(scorer.predict(x.numpy(), chunk=7), whole, rtol=1e-6, atol=1e-7)
    assert scorer.predict(x, chunk=7).shape == (50, 3)  # the last, short chunk included


OVERRIDES = [
    "reward=r2",
    "agent=chooser",
    "agent.chooser.episodes=4",
    "agent.chooser.steers=[1.0]",
    "agent.chooser.lane_change_s=[0.3]",
    "agent.chooser.swerve=true",
    "agent.chooser.mask_view=true",
    "env.tele_fov_deg=30",  # the frame band from the narrow second camera
    "agent.chooser.mask_camera=tele",
    "agent.chooser.target=advantage",
    "agent.chooser.aux_weight=1.0",
    "agent.chooser.decide_s=0.5",
    "agent.chooser.steps=250",
    "agent.chooser.batch_size=16",
]


@pytest.fixture(scope="module")
def trained(smoke_builds, tmp_path_factory):
    """A chooser trained on the smoke world model (4 labelled episodes, 1 worker)."""
    from worldmodel.config import compose

    root = tmp_path_factory.mktemp("chooser")
    shutil.copytree(smoke_builds("rnn"), root, dirs_exist_ok=True)
    base = [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke", "threads=1"]
    cfg = compose("train_agent", [*base, *OVERRIDES, "agent.chooser.num_workers=1"])
    metrics = train_agent.run(cfg)
    return root, base, cfg, metrics


def test_labels_are_reproducible_for_any_worker_count(trained, stage_cfg, tmp_path):
    _, _, cfg, metrics = trained
    assert metrics["learner"] == "chooser" and metrics["labelled_episodes"] == 4
    again = stage_cfg("train_agent", *OVERRIDES, "agent.chooser.num_workers=2", root=tmp_path)
    a, b = chooser.labels(cfg), chooser.labels(again)
    for key in (*chooser.LABEL_KEYS, chooser.TELE_KEY):
        np.testing.assert_array_equal(a[key], b[key])
    assert a[chooser.TELE_KEY].shape == a["seg"].shape and (a[chooser.TELE_KEY] != a["seg"]).any()
    assert a["costs"].shape[1] == len(CANDIDATES) and a["t"].max() < decide_steps_for(0.5)
    # a corrupt shard is named, with what to do
    shard = next(chooser.labels_dir(again).glob("shard_*.h5"))
    shard.write_bytes(b"not hdf5")
    with pytest.raises(StageError, match="delete it and rerun"):
        chooser.labels(again)


def test_more_episodes_label_what_a_shard_lacks(trained, tmp_path):
    """Labels made for 4 episodes are read again as they are; asked for 5, the shard is labelled again in full, so
    the labels hold every episode asked for and the first four as they were."""
    from worldmodel.config import compose

    root, base, cfg, _ = trained
    shutil.copytree(root / "data", tmp_path / "data")
    paths = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs"]
    same = compose("train_agent", [*paths, *base[2:], *OVERRIDES, "agent.chooser.num_workers=1"])
    shard = chooser.labels_dir(same) / "shard_0000.h5"
    made = shard.read_bytes()
    four = chooser.labels(same)
    assert shard.read_bytes() == made  # the episodes it holds are the ones asked for: read, not labelled again
    more = same.copy()
    more.agent.chooser.episodes = 5
    five = chooser.labels(more)
    assert sorted(set(five["episode"].tolist())) == [0, 1, 2, 3, 4]
    kept = five["episode"] < 4
    for key in chooser.LABEL_KEYS:
        np.testing.assert_array_equal(five[key][kept], four[key])


def test_trained_chooser_acts_on_the_inputs_it_was_trained_on(trained):
    """Evaluation finds the chooser, and its live scores on a labelled episode equal the scorer applied offline to
    the encoded labels (same world-model state, same frame band, same normalisation)."""
    _, base, cfg, _ = trained
    from worldmodel.config import compose

    agent = artifacts.AgentId.of(cfg)
    assert agent.key == "agent_r2_chooser/seed0"
    ecfg = compose("evaluate", base)
    policy, _, models = policies.policy_for(ecfg, agent.key)
    assert isinstance(policy, ManoeuvreChooser) and models["actor_sha"]
    data = chooser.labels(cfg)
    rows = np.flatnonzero(data["episode"] == 0)
    encoder = loading.load_world_model(cfg)
    offline_x = chooser.scorer_inputs(encoder, data, policy.decide_steps, True, "tele")[rows]
    band = offline_x[:, -policy.scores.mask.dim :].reshape(-1, *policy.scores.mask.shape)
    classes = [CLASS_NAMES.index(c) for c in HAZARD_CLASSES]
    np.testing.assert_array_equal(
        band[0, : len(classes)], data[chooser.TELE_KEY][rows[0], 8:48] == np.array(classes)[:, None, None]
    )
    with torch.no_grad():
        offline = policy.scores.scorer(torch.from_numpy(offline_x)).numpy()
    # the same episode live: the policy never commits (huge margin), so it brakes exactly as labelled
    policy.margin = 1e9
    seen = []
    inner = policy.scores
    policy.scores = lambda obs, t: seen.append(inner(obs, t)) or seen[-1]
    # evaluation makes the policy's env with the second camera it was trained with, unasked
    assert policies.env_overrides(policy) == {"tele_fov_deg": 30.0}
    env = make_env(ecfg, camera=True, **policies.env_overrides(policy))
    rollout(env, policy, chooser.label_scenario(int(cfg.seed), 0, chooser.cfg_chooser(cfg)))
    np.testing.assert_allclose(np.stack(seen)[: len(rows)], offline, atol=1e-4)
    # without the second camera, the chooser says what to set; labels without its frames likewise
    wide_env = make_env(ecfg, camera=True)
    policy.scores = inner
    with pytest.raises(StageError, match="env.tele_fov_deg"):
        rollout(wide_env, policy, chooser.label_scenario(int(cfg.seed), 0, chooser.cfg_chooser(cfg)))
    with pytest.raises(StageError, match="env.tele_fov_deg"):
        chooser.scorer_inputs(encoder, {k: v for k, v in data.items() if k != chooser.TELE_KEY}, 3, True, "tele")
    # a chooser needs R2
    with pytest.raises(StageError, match="reward=r2"):
        train_agent.run(compose("train_agent", [*base, *OVERRIDES, "reward=r1", "agent.variant=chooserr1"]))


def test_a_trained_chooser_that_switches_late_costs_offline_what_it_costs_live(trained):
    """policy_cost on the labels is the exact R2 cost of a live episode also when the learned scorer switches after
    its first frame. The margin is set halfway between the predicted gaps of two frames, so that the switch falls
    on the later one, whatever the scorer learnt, and far from where the live and offline scores (equal to ~1e-5)
    could disagree."""
    _, base, cfg, _ = trained
    from worldmodel.config import compose

    agent = artifacts.AgentId.of(cfg)
    ecfg = compose("evaluate", base)
    policy, _, _ = policies.policy_for(ecfg, agent.key)
    data = chooser.labels(cfg)
    encoder = loading.load_world_model(cfg)
    x = chooser.scorer_inputs(encoder, data, policy.decide_steps, True, "tele")
    with torch.no_grad():
        pred = policy.scores.scorer(torch.from_numpy(x[:])).numpy().astype(np.float64)
    gaps = pred[:, 0] - pred.min(1)  # how much cheaper than braking the cheapest candidate is predicted (switch_choice)
    late = []  # (episode, frame, margin) where a margin lets the first switch fall on that frame, not before
    for e in np.unique(data["episode"]):
        rows = np.flatnonzero((data["episode"] == e) & (data["t"] < policy.decide_steps))
        for j in range(1, len(rows)):
            before = gaps[rows[:j]].max()
            if gaps[rows[j]] - before > 1e-3:
                late.append((int(e), int(data["t"][rows[j]]), (before + gaps[rows[j]]) / 2))
    assert late, "no labelled frame is predicted a larger gap than every frame before it"
    env = make_env(ecfg, camera=True, **policies.env_overrides(policy))
    for e, frame, margin in late[:3]:
        rows = np.flatnonzero(data["episode"] == e)
        window = {"t": data["t"][rows], "steps": policy.decide_steps}
        _, at, _ = chooser.policy_choices(pred[rows], data["episode"][rows], margin, **window)
        assert data["t"][rows][at[0]] == frame
        offline = chooser.policy_cost(pred[rows], data["costs"][rows], data["episode"][rows], margin, **window)
        policy.margin = margin
        live = rollout(env, policy, chooser.label_scenario(int(cfg.seed), e, chooser.cfg_chooser(cfg))).outcome
        assert policy.plan is not None and policy.plan.start == frame
        assert offline[0] == pytest.approx(-live["return_r2"], abs=1e-5)


def test_a_finished_chooser_resumed_with_a_new_floor_keeps_its_scorer(trained, tmp_path):
    """min_brake_cost is a decision-time rule: resuming a finished run with only it changed keeps the fitted scorer
    (same weights, same checks, same held-out predictions) and records the floor; any setting that shapes the fit
    changes the fit identity, so it is refitted."""
    from worldmodel.config import compose

    root, base, cfg, metrics = trained
    shutil.copytree(root, tmp_path, dirs_exist_ok=True)
    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", *base[2:]]
    floored = compose("train_agent", [*base, *OVERRIDES, "agent.chooser.min_brake_cost=0.5", "resume=true"])
    assert chooser.fit_identity(floored) == chooser.fit_identity(cfg)
    assert chooser.fit_identity(compose("train_agent", [*base, *OVERRIDES, "agent.chooser.steps=260"])) != (
        chooser.fit_identity(cfg)
    )
    again = train_agent.run(floored)
    assert again["checks"] == metrics["checks"]
    before = loading.load_agent_state(cfg, artifacts.AgentId.of(cfg), "last")
    after = loading.load_agent_state(floored, artifacts.AgentId.of(floored), "last")
    assert after["min_brake_cost"] == 0.5 and before["min_brake_cost"] == 0.0
    for name, value in before["scorer"].items():
        assert torch.equal(value, after["scorer"][name]), name
    # the same predictions: the floor-free costs on the held-out labels are unchanged
    assert again["held_out_cost"]["learned_by_margin"] == metrics["held_out_cost"]["learned_by_margin"]


def test_static_penalty_needs_labels_with_static_flags(trained, tmp_path):
    """static_penalty shapes the fit (a new fit identity) and is reported with the held-out static rate; on labels
    made before the static flags it stops with what to do."""
    import h5py

    from worldmodel.config import compose

    root, base, cfg, metrics = trained
    assert 0.0 <= metrics["held_out_static"]["learned"] <= 1.0
    shutil.copytree(root, tmp_path, dirs_exist_ok=True)
    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", *base[2:]]
    penalised = compose("train_agent", [*base, *OVERRIDES, "agent.chooser.static_penalty=0.2", "agent.variant=pen"])
    assert chooser.fit_identity(penalised) != chooser.fit_identity(cfg)
    assert chooser.labels_dir(penalised).name == chooser.labels_dir(cfg).name  # the same labels, another target
    for shard in chooser.labels_dir(penalised).glob("shard_*.h5"):
        with h5py.File(shard, "a") as f:
            del f[chooser.STATIC_KEY]
    with pytest.raises(StageError, match="static_penalty=0.2.*relabel"):
        train_agent.run(penalised)


def test_the_scorers_pooling_gives_max_pool_2d_values_and_gradients_before_or_after_its_relu():
    """The frame band's CNN pools with ``MaxPool2x2`` before its ReLU; ``nn.MaxPool2d(2)`` after the ReLU gives
    the same outputs and the same gradients to the input, on maps with ties (whole windows equal, as a sparse band's
    convolutions give) and negative values."""
    from torch import nn

    torch.manual_seed(3)
    x = torch.randn(6, 5, 12, 16)
    x[:, :, :4] = 0.25  # windows of equal values
    x[0, 0, 6, 6] = x[0, 0, 6, 7] = x[0, 0, 7, 6] = 2.0  # a tie for the largest inside one window
    grad = torch.randn(6, 5, 6, 8)
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    reference = nn.MaxPool2d(2)(torch.relu(a))
    ours = torch.relu(chooser_models.MaxPool2x2()(b))
    reference.backward(grad)
    ours.backward(grad)
    assert torch.equal(reference, ours) and torch.equal(a.grad, b.grad)
    with torch.no_grad():
        assert torch.equal(chooser_models.MaxPool2x2()(x), nn.MaxPool2d(2)(x))


def test_the_scorer_inputs_rows_are_what_mask_view_gives_episode_by_episode():
    """``ScorerInputs`` rows (features, then ``band_masks``' masks of this frame and the one before) equal
    ``MaskView`` stepped through each episode from a reset, float for float, also when an episode's rows are not
    contiguous."""
    from envs.views import MaskView

    rng = np.random.default_rng(5)
    seg = rng.integers(0, 13, size=(12, 64, 64)).astype(np.uint8)
    episode = np.array([0, 1, 0, 2, 1, 0, 2, 2, 1, 0, 3, 1])
    vec = rng.normal(size=(12, 3)).astype(np.float32)
    rows = chooser.MASK_ROWS["tele"]
    inputs = chooser_models.ScorerInputs(vec, *chooser.band_masks(seg, episode, rows))
    expected = np.empty(inputs.shape, np.float32)
    for e in np.unique(episode):
        view = MaskView(rows)
        for r in np.flatnonzero(episode == e):
            expected[r] = np.concatenate([vec[r], view(seg[r])])
    np.testing.assert_array_equal(inputs[:], expected)
    held = episode >= 2
    np.testing.assert_array_equal(inputs.subset(held)[[2, 0]], expected[held][[2, 0]])
