"""The paper's DDPG on the true state (``obs=privileged``, ``envs/privileged.py``): the vector reads the simulator
exactly, and the agent trains, is checkpointed and is evaluated without a world model or a camera."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from envs import ScenarioSpec, UrbanCollisionEnv, rollout
from envs.privileged import CORRIDORS, ESCAPE_RANGE_M, PRIVILEGED_DIM, PRIVILEGED_STATE, privileged_state
from envs.scene import LANE_WIDTH, POLES
from worldmodel import artifacts, evaluate, policies, train_agent
from worldmodel.common import StageError
from worldmodel.config import compose, validate
from worldmodel.families.porav import evaluation as porav_eval
from worldmodel.report import read_results_csv

BOTH = ScenarioSpec(seed=11, ttc=1.2, ego_speed=20.0, pedestrian_speed=2.0, p_pedestrian=1.0, p_car=1.0)
EMPTY = ScenarioSpec(seed=5, ttc=1.0, ego_speed=15.0)  # no hazard, no traffic: only the street's static objects


def entry(x: np.ndarray, name: str) -> float:
    return float(x[PRIVILEGED_STATE.index(name)])


@pytest.fixture
def env():
    e = UrbanCollisionEnv(camera=False)
    yield e
    e.close()


def test_the_hazards_are_where_the_simulator_has_them_relative_to_the_ego(env):
    env.reset(options={"scenario": BOTH})
    for _ in range(4):
        env.step([-0.5, -0.3])  # steer left and brake: the ego moves off its lane and turns
    x, e, a = privileged_state(env), env.ego, env.actors
    assert x.shape == (PRIVILEGED_DIM,) and x.dtype == np.float32
    ego_v = np.array([e.v * np.cos(e.psi), e.v * np.sin(e.psi)])
    for who, xy, vel, hazard in (
        ("ped", a.ped_xy, a.ped_vel, a.ped_hazard),
        ("car", a.car_xy, a.car_vel, a.car_hazard),
    ):
        i = int(np.flatnonzero(hazard)[0])
        assert entry(x, who) == 1.0
        assert entry(x, f"{who}_dx") * 40.0 == pytest.approx(xy[i, 0] - e.x, abs=1e-4)
        assert entry(x, f"{who}_dy") * 10.0 == pytest.approx(xy[i, 1] - e.y, abs=1e-4)
        assert entry(x, f"{who}_vx") * 30.0 == pytest.approx(vel[i, 0] - ego_v[0], abs=1e-4)
        assert entry(x, f"{who}_vy") * 10.0 == pytest.approx(vel[i, 1] - ego_v[1], abs=1e-4)
    assert entry(x, "speed") * 30.0 == pytest.approx(e.v, abs=1e-4) and e.v < BOTH.ego_speed
    # steering left (action -0.5) moves the ego to the left of its lane, heading, wheel and yaw all to the left
    assert entry(x, "lane_offset") * LANE_WIDTH == pytest.approx(e.y - env.lane_y, abs=1e-5) and e.y > env.lane_y
    assert entry(x, "heading") == pytest.approx(e.psi, abs=1e-6) and e.psi > 0
    assert entry(x, "steer_angle") * 0.6 == pytest.approx(e.delta, abs=1e-6) and e.delta > 0
    assert entry(x, "yaw_rate") == pytest.approx(e.r, abs=1e-6) and e.r > 0

    env.reset(options={"scenario": EMPTY})  # no hazard: zeros, whatever the ego's speed
    assert not privileged_state(env)[:10].any()


def test_an_obstacle_in_an_escape_corridor_shortens_its_clearance(env):
    env.reset(options={"scenario": EMPTY})
    e, front = env.ego, env.ego.x + env.params.length / 2
    before = privileged_state(env)
    assert entry(before, "own_clear") == 1.0 and entry(before, "own_closing") == 0.0  # the lane ahead is empty
    assert entry(before, "left_clear") == 1.0  # and so is the oncoming one
    # a pole 12 m ahead of the bumper in the middle of the lane to the left, one behind the ego, one beyond the range
    layout = env.layout
    poles = [(front + 12.0, e.y + LANE_WIDTH, 0.12, POLES), (e.x - 10.0, e.y, 0.12, POLES)]
    poles.append((front + ESCAPE_RANGE_M + 5.0, e.y, 0.12, POLES))
    layout.circles = np.concatenate([layout.circles, np.array(poles)])
    x = privileged_state(env)
    assert entry(x, "left_clear") * ESCAPE_RANGE_M == pytest.approx(12.0 - 0.12, abs=1e-4)
    assert entry(x, "left_closing") * 30.0 == pytest.approx(-e.v, abs=1e-4)  # a static object closes at our speed
    assert entry(x, "own_clear") == 1.0  # behind the ego or beyond the range: not in the way
    for side, _ in CORRIDORS:  # the right corridor is the sidewalk, with its poles: untouched
        if side != "left":
            assert entry(x, f"{side}_clear") == entry(before, f"{side}_clear")
    # an active pedestrian walking beside the ego's bumper in its own lane: in the way, at distance 0
    a = env.actors
    a.ped_xy[0], a.ped_vel[0], a.ped_active[0] = (front - 1.0, e.y), (1.0, 0.0), True
    x = privileged_state(env)
    assert entry(x, "own_clear") == 0.0 and entry(x, "own_closing") * 30.0 == pytest.approx(1.0 - e.v, abs=1e-4)


def test_only_the_paper_ddpg_sees_the_true_state_and_its_runs_are_named_for_it():
    cfg = compose("train_agent", ["agent=ddpg", "obs=privileged", "reward=r2"])
    assert validate(cfg).agent.obs == "privileged"
    assert artifacts.AgentId.of(cfg).key == "agent_r2-privileged/seed0"
    assert artifacts.AgentId.parse("agent_r2-privileged/seed0") == artifacts.AgentId("r2", 0, "ddpg", "privileged")
    for refused in ("agent=chooser", "agent.use_speed=true", "agent.frame_view=true", "agent.demo_share=0.2"):
        with pytest.raises(StageError, match="obs"):
            validate(compose("train_agent", ["obs=privileged", refused]))


def test_a_privileged_ddpg_trains_without_a_world_model_and_acts_on_the_true_state(stage_cfg, tmp_path):
    """No world model exists in this experiment: training and evaluation must not ask for one, nor for a camera."""
    agent = artifacts.AgentId("r2", 0, "ddpg", "privileged")
    metrics = train_agent.run(stage_cfg("train_agent", "agent=ddpg", "obs=privileged", "reward=r2"))
    assert metrics["steps"] == 300 and not (tmp_path / "runs/t/vae").exists()
    cfg = stage_cfg("evaluate", "evaluate.policies=[braking]")
    state = torch.load(agent.dir(cfg) / "last.pt", weights_only=False)
    assert (state["obs"], state["obs_dim"]) == ("privileged", PRIVILEGED_DIM)
    assert state["provenance"]["inputs"] == {} == artifacts.read_provenance(agent.dir(cfg))["inputs"]
    assert len(state["buffer"]["obs"]) == 300 and state["buffer"]["obs"].shape[1] == PRIVILEGED_DIM
    assert np.abs(state["buffer"]["obs"]).max() < 5.0  # scaled to about unit range, no camera latents
    assert [a.key for a in artifacts.trained_agents(cfg)] == [agent.key]

    policy, seed, models = policies.policy_for(cfg, agent.key)
    assert not policy.needs_camera and seed == 0
    assert (models["vae_sha"], models["rnn_sha"]) == ("", "") and models["actor_sha"]
    # it acts on privileged_state of the env it is bound to: its actor's output on that vector, step after step
    env = UrbanCollisionEnv(camera=False)
    acted = []

    def check(obs, action, reward, info):
        acted.append(action)

    episode = rollout(env, policy, BOTH, on_step=check)
    assert episode.steps == len(acted) > 1
    env.reset(options={"scenario": BOTH})
    for action in acted[:5]:
        with torch.inference_mode():
            expected = policy.actor(torch.from_numpy(privileged_state(env))[None])[0].numpy()
        np.testing.assert_allclose(action, expected, atol=1e-5)
        env.step(action)
    env.close()

    built, *_ = porav_eval._build(OmegaConf.to_container(cfg, resolve=True), agent.key)  # no camera for it
    assert not built.camera
    built.close()
    evaluate.run(cfg)
    rows = [r for r in read_results_csv(tmp_path / "runs/t/eval/results.csv") if r["policy"] == agent.policy]
    assert len(rows) == len(porav_eval.bank(cfg)) and {(r["vae_sha"], r["rnn_sha"]) for r in rows} == {("", "")}
    assert {r["actor_sha"] for r in rows} == {models["actor_sha"]}
