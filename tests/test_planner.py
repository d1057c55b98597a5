"""The privileged planner: exact re-simulation, never worse than straight-line braking, clear config errors."""

from __future__ import annotations

import numpy as np
import pytest

from envs import ScenarioSpec, StraightLineBraking, UrbanCollisionEnv, rollout
from envs import scenario_bank as make_bank
from envs.planner import Manoeuvre, PrivilegedPlanner, _Plan, candidate_manoeuvres, cost_of_rest, plan_cost
from worldmodel.common import StageError
from worldmodel.config import compose, oracle_settings, validate


def total_injury(outcome: dict) -> float:
    return outcome["pedestrian_injury"] + outcome["occupant_injury"]


def play(env, policy, spec) -> dict:
    return rollout(env, policy, spec).outcome


def test_restore_continues_bit_identically():
    env = UrbanCollisionEnv(camera=False)
    env.reset(options={"scenario": ScenarioSpec(seed=7, ttc=0.9, ego_speed=20.0, p_pedestrian=1.0, p_car=1.0)})
    for _ in range(5):
        env.step([0.3, -0.5])
    snap = env.snapshot()
    twin = env.planning_twin()
    twin.restore(snap)
    actions = [[1.0, -1.0]] * 10 + [[-0.5, 0.2]] * 40
    a, b = [], []
    for act in actions:
        a.append(env.step(act))
        b.append(twin.step(act))
        if a[-1][2] or a[-1][3]:
            break
    assert repr(a) == repr(b)
    assert a[-1][4]["outcome"] == b[-1][4]["outcome"]
    # the snapshot is a copy: stepping the env did not change it, so restoring again replays the same steps
    twin.restore(snap)
    assert repr(twin.step(actions[0])) == repr(a[0])


def test_the_committed_plans_cost_read_from_its_rollout_is_what_simulating_it_again_gives():
    """The planner keeps the rewards of the rollout that chose its plan and reads the plan's remaining cost from
    them at the next replan instead of simulating it again. At every step of seeded episodes that cost is the
    float a fresh simulation from the env's present state gives."""
    env = UrbanCollisionEnv(camera=False)
    planner = PrivilegedPlanner(replan_every=3)
    checked = 0
    for entry in make_bank(ttcs=(0.5, 1.0), speeds=(25.0,), per_cell=1, seed=77):
        env.reset(options={"scenario": entry.spec})
        planner.reset()
        planner.bind(env)
        reference = env.planning_twin()
        done = False
        while not done:
            action = planner.act(None, None)
            chosen_at, trace = planner._trace
            assert cost_of_rest(trace, env.t_step - chosen_at) == plan_cost(reference, env.snapshot(), planner.plan)
            checked += 1
            _, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    assert checked > 20


def test_a_delayed_manoeuvre_continued_from_the_straight_rollout_costs_what_simulating_it_whole_gives():
    """A steering manoeuvre that starts after a delay acts as the straight one with its pedal until then: the planner
    continues that rollout from its kept snapshot. Cost and rewards are the floats of the whole simulation, for
    every bound (those that cut either part short included)."""
    env = UrbanCollisionEnv(camera=False)
    twin = env.planning_twin()
    delayed = [m for m in candidate_manoeuvres() if m.steer and m.delay]
    checked = 0
    for entry in make_bank(ttcs=(0.5, 1.0), speeds=(15.0, 25.0), per_cell=1, seed=78):
        env.reset(options={"scenario": entry.spec})
        for _ in range(2):
            env.step([0.0, -1.0])
        snap, t = env.snapshot(), env.t_step
        for m in delayed[::12]:
            first, keep = [], {m.delay: None}
            plan_cost(twin, snap, _Plan(Manoeuvre(m.pedal), t), trace=first, keep=keep)
            if keep[m.delay] is None:  # the straight rollout ended first: nothing to continue
                continue
            for bound in (np.inf, 0.05, 1e-6):
                whole, continued = [], []
                expected = plan_cost(twin, snap, _Plan(m, t), bound, trace=whole)
                start = (first[: m.delay], keep[m.delay])
                assert plan_cost(twin, snap, _Plan(m, t), bound, trace=continued, start=start) == expected
                assert continued == whole
                checked += 1
    assert checked > 20


def test_the_evaluation_planner_is_never_worse_than_braking_where_braking_leaves_injury(tmp_path):
    """Braking is the planner's first candidate and it only switches to a plan the exact re-simulation finds
    strictly cheaper, so on every scenario its total injury is at most braking's. Checked one by one on every bank
    scenario of the short-TTC, 20 m/s cells (all three hazards) where braking leaves some injury, with the planner
    the evaluation builds from the config."""
    cfg = compose("evaluate", [f"paths.data_root={tmp_path}", f"paths.runs_root={tmp_path}", "scale=smoke"])
    planner = PrivilegedPlanner.from_settings(**oracle_settings(cfg))
    env = UrbanCollisionEnv(camera=False)
    assert planner.step_s == env.step_s
    checked, improved, worse = 0, 0, []
    for entry in make_bank(ttcs=(0.5, 0.75), speeds=(20.0,), per_cell=4, seed=2018):
        braking = total_injury(play(env, StraightLineBraking(), entry.spec))
        if braking <= 0.0:
            continue
        checked += 1
        planned = total_injury(play(env, planner, entry.spec))
        improved += planned < braking - 1e-9
        if planned > braking + 1e-9:
            worse.append((entry.scenario_id, entry.hazard, entry.ttc, entry.speed, braking, planned))
    assert checked >= 20, checked
    assert worse == []
    assert improved > 0  # a planner that only ever braked would meet the bound above on every scenario


def test_candidates_start_with_braking_and_config_is_checked():
    cands = candidate_manoeuvres()
    assert cands[0] == Manoeuvre(-1.0)
    assert all(np.array_equal(cands[0].action(k), [0.0, -1.0]) for k in range(50))
    lane_change = Manoeuvre(-1.0, 0.5, delay=2, shape="lane_change", hold=3)
    assert [float(lane_change.action(k)[0]) for k in range(10)] == [0, 0, 0.5, 0.5, 0.5, -0.5, -0.5, -0.5, 0, 0]
    with pytest.raises(ValueError, match="-1.0"):
        candidate_manoeuvres(pedals=(0.0, -0.5))
    with pytest.raises(ValueError, match="steers"):
        candidate_manoeuvres(steers=(1.5,))
    with pytest.raises(RuntimeError, match="bind"):
        PrivilegedPlanner().act({}, {})


def test_evaluation_config_for_the_planner_is_validated(tmp_path):
    def cfg(*overrides):
        return compose(
            "evaluate", [f"paths.data_root={tmp_path}", f"paths.runs_root={tmp_path}", "scale=smoke", *overrides]
        )

    with pytest.raises(StageError, match="evaluate.policies"):
        validate(cfg("evaluate.policies=[oracle]"))
    with pytest.raises(StageError, match="evaluate.oracle.*-1.0"):
        validate(cfg("evaluate.oracle.pedals=[0.0]"))
    with pytest.raises(StageError, match="evaluate.oracle.replan_every_s"):
        validate(cfg("evaluate.oracle.replan_every_s=0"))
    validate(cfg())


def test_perception_ceiling_brakes_straight_for_its_first_frames_then_plans():
    """brake_first=k: the planner a camera policy could be if it needed k frames to see the hazard."""
    env = UrbanCollisionEnv(camera=False)
    spec = ScenarioSpec(seed=5, ttc=0.75, ego_speed=30.0, pedestrian_speed=2.0, p_pedestrian=1.0)
    actions = {}
    for k in (0, 2):
        seen = []
        # a small candidate set keeps the test quick: full brake, hold, and an immediate hard swerve either way
        planner = PrivilegedPlanner(
            brake_first=k, pedals=(-1.0, 0.0), steers=(1.0,), delays_s=(0.0,), lane_change_s=(0.3,)
        )
        rollout(env, planner, spec, on_step=lambda o, a, r, i, s=seen: s.append(a))
        actions[k] = np.array(seen)
    assert np.abs(actions[0][:3, 0]).max() > 0  # at 30 m/s and TTC 0.75 s the planner swerves at once
    np.testing.assert_array_equal(actions[2][:2], [[0.0, -1.0], [0.0, -1.0]])
    assert np.abs(actions[2][2:, 0]).max() > 0  # and then it still plans
    with pytest.raises(ValueError, match="brake_first"):
        PrivilegedPlanner(brake_first=-1)


def test_camera_cap_brakes_straight_until_the_hazard_covers_k_pixels_then_plans():
    """brake_until_pixels=K (``oracle_pixelsK``): straight braking until the hazard covers K pixels of the rendered
    frame, then the planner, which keeps planning when the hazard leaves the frame again. On the real camera."""
    env = UrbanCollisionEnv()  # the camera on: the cap reads the rendered frame
    spec = ScenarioSpec(seed=5, ttc=0.75, ego_speed=30.0, pedestrian_speed=2.0, p_pedestrian=1.0)
    small = {"pedals": (-1.0, 0.0), "steers": (1.0,), "delays_s": (0.0,), "lane_change_s": (0.3,)}

    def drive(policy):
        """(actions, the hazard's pixels in the frame each action was chosen on, outcome)."""
        actions, pixels = [], []
        episode = rollout(
            env,
            policy,
            spec,
            on_reset=lambda o, i: pixels.append(env.hazard_pixels()),
            on_step=lambda o, a, r, i: (actions.append(np.asarray(a)), pixels.append(env.hazard_pixels())),
        )
        return np.array(actions), np.array(pixels[: len(actions)]), episode.outcome

    try:
        # a hazard that never covers that many pixels: straight braking throughout, braking's episode exactly
        never = PrivilegedPlanner(brake_until_pixels=64 * 64 + 1, **small)
        assert never.name == "oracle_pixels4097" and never.needs_camera
        actions, _, outcome = drive(never)
        np.testing.assert_array_equal(actions, np.tile([0.0, -1.0], (len(actions), 1)))
        assert repr(outcome) == repr(drive(StraightLineBraking())[2])

        # K = 1: braking until the first frame where the pedestrian covers a pixel, then the planner's actions,
        # which are those of a planner that brakes for exactly that many frames (replanning every step in both)
        actions, pixels, _ = drive(PrivilegedPlanner(brake_until_pixels=1, replan_every=1, **small))
        first = int(np.flatnonzero(pixels >= 1)[0])
        assert first > 0  # hidden at onset in this scenario, so the cap has something to wait for
        np.testing.assert_array_equal(actions[:first], np.tile([0.0, -1.0], (first, 1)))
        reference, _, _ = drive(PrivilegedPlanner(brake_first=first, replan_every=1, **small))
        np.testing.assert_array_equal(actions, reference)
        assert np.abs(actions[first:, 0]).max() > 0  # it does plan: it steers
        assert pixels[first:].min() == 0  # and the hazard leaves the frame later without it going back to braking
    finally:
        env.close()

    with pytest.raises(ValueError, match="camera"):
        rollout(UrbanCollisionEnv(camera=False), PrivilegedPlanner(brake_until_pixels=1), spec)
    with pytest.raises(ValueError, match="brake_until_pixels"):
        PrivilegedPlanner(brake_until_pixels=-1)


def test_the_camera_cap_is_a_scripted_policy_evaluated_with_the_camera(tmp_path):
    """``evaluate.policies`` takes oracle_pixels1 and oracle_pixels3; evaluation builds them on an env with the
    camera (they read its frame) and the planner itself without; their rows get a label of their own."""
    from worldmodel.families.porav import evaluation as porav_eval
    from worldmodel.policies import policy_for
    from worldmodel.report import policy_label

    overrides = [f"paths.data_root={tmp_path}", f"paths.runs_root={tmp_path}", "scale=smoke"]
    cfg = compose("evaluate", [*overrides, "evaluate.policies=[braking,oracle,oracle_pixels1,oracle_pixels3]"])
    validate(cfg)
    policy, _, _ = policy_for(cfg, "oracle_pixels3")
    assert (policy.name, policy.brake_until_pixels, policy.brake_first) == ("oracle_pixels3", 3, 0)
    assert "camera cap" in policy_label("oracle_pixels1") and "3 px" in policy_label("oracle_pixels3")
    from omegaconf import OmegaConf

    cfg_dict = OmegaConf.to_container(cfg, resolve=True)
    for name, camera in (("oracle", False), ("oracle_pixels1", True)):
        env, policy, _, _ = porav_eval._build(cfg_dict, name)
        try:
            assert (env.camera, policy.name) == (camera, name)
        finally:
            env.close()


def test_a_one_sided_teacher_steers_only_to_its_side(tmp_path):
    """demos.teacher_sides: the planner that demonstrates starts its manoeuvres only to the sides asked for, and its
    store is kept apart from the two-sided one; the evaluation planner (the ceiling) is unchanged."""
    from worldmodel import artifacts
    from worldmodel.config import oracle_settings, teacher_settings

    right = candidate_manoeuvres(sides=(1.0,))
    both = candidate_manoeuvres()
    assert all(m.steer >= 0 for m in right) and len(both) == 2 * len(right) - 4  # the 4 straight pedals are shared
    with pytest.raises(ValueError, match="sides"):
        candidate_manoeuvres(sides=(1.0, 1.0))
    with pytest.raises(ValueError, match="sides"):
        candidate_manoeuvres(sides=(0.5,))

    env = UrbanCollisionEnv(camera=False)
    spec = ScenarioSpec(seed=5, ttc=0.75, ego_speed=30.0, pedestrian_speed=2.0, p_pedestrian=1.0)
    small = {"pedals": (-1.0, 0.0), "steers": (1.0,), "delays_s": (0.0,), "lane_change_s": (0.3,)}
    for side in (1.0, -1.0):
        seen = []
        rollout(env, PrivilegedPlanner(sides=(side,), **small), spec, on_step=lambda o, a, r, i, s=seen: s.append(a))
        steer = np.array(seen)[:, 0]
        assert steer[np.flatnonzero(steer)[0]] == side  # it steers to its side first (a lane change counter-steers)

    def cfg(*overrides):
        return compose("demonstrate", [f"paths.data_root={tmp_path}", f"paths.runs_root={tmp_path}", *overrides])

    default, one = cfg(), cfg("demos.teacher_sides=[1.0]")
    assert teacher_settings(default) == {k: v for k, v in oracle_settings(default).items() if k != "brake_first"}
    assert teacher_settings(one)["sides"] == [1.0] and "sides" not in oracle_settings(one)
    assert (artifacts.demos_dir(default).name, artifacts.demos_dir(one).name) == ("demos", "demos_right")
    with pytest.raises(StageError, match="demos.teacher_sides"):
        validate(cfg("demos.teacher_sides=[1.0,1.0]"))


def test_a_teacher_without_later_starts_labels_what_to_do_now(tmp_path):
    """demos.teacher_delays_s: the teacher's steering delays replace evaluate.oracle's (so a label made from scratch
    never postpones the steering), its store and a LIDAR agent's provenance say so, and null changes nothing."""
    from worldmodel import artifacts
    from worldmodel.config import oracle_settings, teacher_settings

    def cfg(*overrides):
        return compose(
            "train_agent",
            [f"paths.data_root={tmp_path}", f"paths.runs_root={tmp_path}", "agent=ddpg_kim_fd", *overrides],
        )

    default, now = cfg(), cfg("demos.teacher_delays_s=[0.0]")
    planner = lambda c: PrivilegedPlanner.from_settings(**teacher_settings(c))  # noqa: E731
    assert any(m.delay > 0 for m in planner(default).candidates)
    assert all(m.delay == 0 for m in planner(now).candidates)
    assert oracle_settings(now) == oracle_settings(default)  # the ceiling is evaluate.oracle's, unchanged
    assert teacher_settings(cfg("demos.teacher_delays_s=null")) == teacher_settings(default)
    assert (artifacts.demos_dir(default).name, artifacts.demos_dir(now).name) == ("demos", "demos_delays0")
    assert artifacts.demos_dir(cfg("demos.teacher_sides=[1.0]", "demos.teacher_delays_s=[0.0,0.2]")).name == (
        "demos_right_delays0-0.2"
    )
    assert artifacts.provenance(now, "agent") != artifacts.provenance(default, "agent")
    assert artifacts.provenance(cfg("demos.teacher_delays_s=null"), "agent") == artifacts.provenance(default, "agent")
    for bad in ("[]", "[-0.1]"):
        with pytest.raises(StageError, match="demos.teacher_delays_s"):
            validate(cfg(f"demos.teacher_delays_s={bad}"))
    with pytest.raises(StageError, match="agent.kim.bc_steer_weight"):
        validate(cfg("agent.kim.bc_steer_weight=0"))
    with pytest.raises(StageError, match="agent.kim.bc_steer_weight"):
        validate(cfg("agent=dag", "agent.kim.bc_steer_weight=5"))  # a camera student: no steering label here
    assert artifacts.provenance(cfg("agent.kim.bc_steer_weight=1"), "agent") == artifacts.provenance(default, "agent")
    assert artifacts.provenance(cfg("agent.kim.bc_steer_weight=5"), "agent") != artifacts.provenance(default, "agent")
