"""Scenario family ``merola`` (envs/merola.py) on the real simulator: each scenario's hazard as specified, replay,
the reward, the nine actions, and the ResNet-18 observation's refusal without weights."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from envs import UrbanCollisionEnv, rollout
from envs.families import spec_from_dict
from envs.merola import DRIFT_AFTER_S, SCENARIOS, BrakeThenRelease, Hold, MerolaSpec, sample
from envs.policies import ConstantAction
from envs.rewards import MEROLA_IMPACT_FULL_MS, MEROLA_V_MIN, StepContext, merola
from envs.scene import EGO_LANE_Y, ONCOMING_LANE_Y
from worldmodel.common import StageError
from worldmodel.families.merola.system import ACTIONS, merola_action
from worldmodel.models.resnet import ResNet18Features, load_resnet18

HOLD, BRAKE = (0.0, 0.0), (0.0, -1.0)


@pytest.fixture(scope="module")
def env():
    return UrbanCollisionEnv(camera=False, step_s=0.1, family="merola", reward="merola")


def spec_of(scenario: str, **fields) -> MerolaSpec:
    base = {"seed": 4, "scenario": scenario, "ego_speed": 12.0, "other_speed": 14.0, "ttc": 1.5}
    return MerolaSpec(**{**base, **fields})


def car_track(env, spec, action, steps: int) -> np.ndarray:
    """The other car's (x, y) at the start and after every step while nothing is hit."""
    env.reset(options={"scenario": spec})
    out = [env.actors.car_xy[0].copy()]
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
        out.append(env.actors.car_xy[0].copy())
    return np.array(out)


def test_the_lead_car_brakes_at_its_deceleration_to_a_stop(env):
    spec = spec_of("lead_brake", ttc=2.0, lead_decel=7.0, other_speed=12.0)
    x = car_track(env, spec, BRAKE, 25)[:, 0]
    v = np.diff(x) / 0.1  # mean speed over each step
    t_mid = 0.1 * (np.arange(len(v)) + 0.5)
    moving = t_mid < 12.0 / 7.0 - 0.1
    np.testing.assert_allclose(v[moving], 12.0 - 7.0 * t_mid[moving], rtol=1e-9)
    assert np.all(np.abs(v[t_mid > 12.0 / 7.0 + 0.1]) < 1e-9)
    assert x[-1] - x[0] == pytest.approx(12.0**2 / (2 * 7.0), rel=1e-9)
    assert not env.collisions  # the ego braked from the start and had 2 s of headway


@pytest.mark.parametrize("from_left", [False, True])
def test_the_crossing_car_meets_a_coasting_ego_at_its_ttc(from_left):
    """Footprints first overlap within one sub-step after the scenario's TTC (1 ms with 100 sub-steps; they touch at
    the TTC), at the family's fastest speeds, from either side; the crossing car is the hazard."""
    fine = UrbanCollisionEnv(camera=False, step_s=0.1, family="merola", substeps=100)
    for ttc in (1.0, 2.5):
        spec = spec_of("crossing", ttc=ttc, ego_speed=60 / 3.6, other_speed=60 / 3.6, from_left=from_left)
        rollout(fine, ConstantAction(HOLD), spec)
        hit = fine.collisions[0]
        assert hit["hazard"] and hit["class"] == "Vehicles"
        assert ttc - 1e-9 <= hit["time"] <= ttc + 0.001 + 1e-9, (ttc, hit["time"])  # they touch at ttc
        assert hit["ego_side"] == "front"
    assert abs(fine.layout.junction_x - fine.family_state.motion.x0) == pytest.approx(1.75)


def test_the_oncoming_car_drifts_into_the_ego_lane_at_its_lateral_speed(env):
    spec = spec_of("drift", ttc=2.0, drift_speed=3.0, ego_speed=10.0, other_speed=10.0)
    env.reset(options={"scenario": spec})
    gap = env.actors.car_xy[0, 0] - 4.5 / 2 - (env.ego.x + env.params.length / 2)
    assert gap / (10.0 + 10.0) == pytest.approx(spec.ttc + DRIFT_AFTER_S, rel=1e-9)  # TTC 2 s when the drift starts
    xy = car_track(env, spec, BRAKE, 25)
    vy = np.diff(xy[:, 1]) / 0.1
    t0 = 0.1 * np.arange(len(vy))
    assert np.all(np.abs(vy[t0 + 0.1 <= DRIFT_AFTER_S + 1e-9]) < 1e-9)
    lateral_s = (ONCOMING_LANE_Y - EGO_LANE_Y) / 3.0
    during = (t0 >= DRIFT_AFTER_S - 1e-9) & (t0 + 0.1 <= DRIFT_AFTER_S + lateral_s)
    assert during.sum() >= 10
    np.testing.assert_allclose(vy[during], -3.0, rtol=1e-9)
    assert xy[-1, 1] == pytest.approx(EGO_LANE_Y) and np.all(xy[:, 1] >= EGO_LANE_Y - 1e-9)
    np.testing.assert_allclose(np.diff(xy[:, 0]) / 0.1, -10.0, rtol=1e-9)  # its speed along the road holds


def test_specs_validate_sample_every_scenario_and_replay_bit_identically(env):
    rng = np.random.default_rng(1)
    specs = [sample(rng) for _ in range(30)]
    assert {s.scenario for s in specs} == set(SCENARIOS)
    assert all(s.at_junction for s in specs if s.scenario == "crossing")
    assert spec_from_dict(specs[0].to_dict()) == specs[0]
    for field_name, bad in (("scenario", "tailgate"), ("ego_speed", 0.0), ("ttc", -1.0), ("at_junction", 1)):
        with pytest.raises(ValueError, match=field_name):
            MerolaSpec(**{**specs[0].to_dict(), field_name: bad})
    first = [(rollout(env, ConstantAction([0.2, -0.5]), s).outcome, list(env.collisions)) for s in specs[:6]]
    again = [(rollout(env, ConstantAction([0.2, -0.5]), s).outcome, list(env.collisions)) for s in specs[:6]]
    assert json.dumps(first, default=float) == json.dumps(again, default=float)


def test_the_camera_draws_the_family_and_sees_the_crossing_car():
    cam = UrbanCollisionEnv(camera=True, step_s=0.1, family="merola")
    obs, _ = cam.reset(options={"scenario": spec_of("crossing", ttc=1.0, from_left=True)})
    for _ in range(3):
        obs, *_ = cam.step(HOLD)
    assert (np.asarray(obs["seg"]) == 10).sum() > 20  # Vehicles: the car crossing in front
    cam.close()


def test_merola_reward_by_hand():
    """+1 per metre (the step's mean speed times its length), -5 for braking under 2 m/s or throttle over 60 km/h,
    -1 for steering further off the road beyond 10°, and minus clip(100 dv / 16.67, 1, 100) per crash."""

    def r(action, v0=10.0, v1=10.0, heading=0.0, hits=()):
        return merola(StepContext(list(hits), v0, v1, np.array(action, float), 0.1, {}, heading))

    assert r((0.0, 0.0)) == pytest.approx(1.0)
    assert r((0.0, -1.0), 2.0, 1.0) == pytest.approx(0.15 - 5.0)
    assert r((0.0, 1.0), 17.0, 17.0) == pytest.approx(1.7 - 5.0)
    left = math.radians(15.0)
    assert r((-0.5, 0.0), heading=left) == pytest.approx(0.0)  # steering left while pointing left: further off
    assert r((0.5, 0.0), heading=left) == pytest.approx(1.0)  # steering back
    assert r((0.5, 0.0), heading=math.radians(5.0)) == pytest.approx(1.0)  # within 10°
    crash = {"kind": "vehicle", "delta_v_ego": 0.5 * MEROLA_IMPACT_FULL_MS, "impact_speed": 10.0}
    assert r((0.0, 0.0), hits=[crash]) == pytest.approx(1.0 - 50.0)
    assert r((0.0, 0.0), hits=[{**crash, "delta_v_ego": 0.01}]) == pytest.approx(0.0)  # at least 1
    assert r((0.0, 0.0), hits=[{**crash, "delta_v_ego": 40.0}]) == pytest.approx(1.0 - 100.0)  # at most 100


@pytest.mark.parametrize("side", [1.0, -1.0])  # pointing left (positive heading) or right
def test_merola_heading_penalty_starts_beyond_10_degrees(side):
    """Steering further off the road costs 1 only beyond 10°: at 9.9° (and at 10° itself) the step earns its full
    +1 for the metre travelled, at 10.1° it earns 0. Steering back or holding the wheel straight never costs."""

    def r(steer, degrees):
        return merola(StepContext([], 10.0, 10.0, np.array([steer, 0.0]), 0.1, {}, math.radians(degrees)))

    further = -0.5 * side  # a positive steer turns right, lowering the heading
    assert r(further, 9.9 * side) == pytest.approx(1.0)
    assert r(further, 10.0 * side) == pytest.approx(1.0)
    assert r(further, 10.1 * side) == pytest.approx(0.0)
    assert r(further, 60.0 * side) == pytest.approx(0.0)
    assert r(-further, 10.1 * side) == pytest.approx(1.0)
    assert r(0.0, 10.1 * side) == pytest.approx(1.0)


def test_the_nine_actions_are_brake_none_throttle_by_left_straight_right():
    assert ACTIONS.shape == (9, 2) and len({tuple(a) for a in ACTIONS}) == 9
    assert set(ACTIONS[:, 1]) == {-1.0, 0.0, 1.0} and set(ACTIONS[:, 0]) == {-0.5, 0.0, 0.5}
    assert list(merola_action(4)) == [0.0, 0.0]


def test_resnet_observation_refuses_without_weights_and_loads_a_state_dict(tmp_path):
    with pytest.raises(StageError, match="agent.merola.resnet_weights"):
        load_resnet18(None)
    with pytest.raises(StageError, match="no such file"):
        load_resnet18(str(tmp_path / "missing.pth"))
    torch.manual_seed(0)
    net = ResNet18Features()
    state = {k: v for k, v in net.state_dict().items() if not k.endswith("num_batches_tracked")}
    state["fc.weight"] = torch.zeros(1000, 512)  # torchvision's classifier: ignored
    torch.save(state, tmp_path / "r18.pth")
    loaded = load_resnet18(str(tmp_path / "r18.pth"))
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(loaded(x), net.eval()(x)) and loaded(x).shape == (2, 512, 2, 2)
    torch.save({"conv1.weight": torch.zeros(3)}, tmp_path / "other.pth")
    with pytest.raises(StageError, match="not a ResNet-18"):
        load_resnet18(str(tmp_path / "other.pth"))


def test_braking_that_lets_go_below_v_min_never_pays_for_braking_and_holding_never_brakes(env):
    """The policies the reward is read against (docs/results/merola/reward/): on a lead car braking to a stop with
    room to spare, brake_release brakes exactly while the ego is at or above the reward's v_min, so it stops clear
    of the lead car as braking does, but is never charged the -5 that braking pays for every step of braking once
    slow; hold never touches the pedal."""
    from envs.policies import StraightLineBraking

    spec = spec_of("lead_brake", ttc=2.0, lead_decel=7.0, other_speed=12.0)

    def drive(policy, stops: bool = True) -> list[tuple[float, float, float]]:
        """(speed before, pedal, reward) of every step; a policy that ``stops`` is to end clear of the lead car."""
        steps, speed = [], []
        rollout(
            env,
            policy,
            spec,
            on_reset=lambda obs, info: speed.append(env.ego.v),
            on_step=lambda obs, action, reward, info: (
                steps.append((speed[-1], float(action[1]), float(reward))),
                speed.append(env.ego.v),
            ),
        )
        assert not (stops and env.collisions), f"{policy.name} should stop clear of the lead car"
        return steps

    released, braked = drive(BrakeThenRelease()), drive(StraightLineBraking())
    assert all((pedal < 0) == (v >= MEROLA_V_MIN) for v, pedal, _ in released)
    assert any(pedal == 0 for _, pedal, _ in released)
    charged = sum(1 for v, pedal, r in braked if pedal < 0 and r <= -5 + 1e-9)
    assert charged > 10  # braking, once slow, pays on every step left
    assert sum(r for *_, r in released) > sum(r for *_, r in braked) + 5 * (charged - 1)
    assert all(pedal == 0 for _, pedal, _ in drive(Hold(), stops=False))


def test_merola_safe_costs_a_crash_100_more_and_nothing_else():
    """The deviation (reward=merola_safe) changes the crash term only: a crash outweighs any episode's progress."""
    from envs.rewards import MEROLA_MOST_PROGRESS, merola_safe

    hit = {"kind": "vehicle", "delta_v_ego": 3.0}
    for hits in ([], [hit], [hit, hit]):
        ctx = StepContext(hits, 10.0, 9.0, np.array([0.2, -1.0]), 0.1, heading=0.3)
        assert merola_safe(ctx) == pytest.approx(merola(ctx) - 100.0 * len(hits))
    assert MEROLA_MOST_PROGRESS == pytest.approx(6.0 * 60.0 / 3.6)  # the 6 s horizon at the ego's top speed


def test_privileged_ddqn_trains_and_its_re_simulated_values_match_the_episode(stage_cfg):
    """agent=ddqn_merola obs=privileged reward=merola_safe trains without the camera; for the action it takes,
    experiments/merola_q_vs_exact's re-simulated Q^pi is the discounted return of the rest of its own episode."""
    from experiments import merola_q_vs_exact as q_vs_exact
    from worldmodel import artifacts, train_agent
    from worldmodel.families.merola import system

    overrides = ("agent=ddqn_merola", "obs=privileged", "reward=merola_safe", "agent.dqn.warmup_steps=40")
    cfg = stage_cfg("train_agent", *overrides)
    train_agent.run(cfg)
    (agent,) = artifacts.trained_agents(cfg, family="merola")
    assert agent.key == "agent_merola_safe_ddqn_merola-privileged/seed0"
    policy = system.load_policy(cfg, agent)
    gamma = float(policy.agent.cfg.gamma)
    env = system.family_env(cfg, step_s=0.1, camera=False, reward="merola_safe")
    spec = sample(np.random.default_rng(3), "drift")
    q, exact, steps = q_vs_exact.episode_values(env, env.planning_twin(), policy, spec, 4, gamma)
    assert steps[:2] == [0, 4] and np.shape(exact) == (len(steps), 9)
    # the greedy episode itself, its discounted return from each valued step on
    obs, _ = env.reset(options={"scenario": spec})
    policy.reset()
    policy.bind(env)
    rewards, done = [], False
    while not done:
        obs, r, terminated, truncated, _ = env.step(policy.act(obs, None))
        rewards.append(r)
        done = terminated or truncated
    env.close()
    for row, t in enumerate(steps):
        taken = q_vs_exact.ORDER.index(int(np.argmax(q[row][np.argsort(q_vs_exact.ORDER)])))
        rest = sum(r * gamma**k for k, r in enumerate(rewards[t:]))
        assert exact[row][taken] == pytest.approx(rest, abs=1e-6), (t, exact[row], rest)
