"""What the actor's output means: the braking anchor and grip-scaled steering (``worldmodel/action_map.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from envs import StraightLineBraking, UrbanCollisionEnv, rollout, scenario_bank
from envs.vehicle import G, VehicleParams
from worldmodel.action_map import ActionMap
from worldmodel.agent_obs import LearnedPolicy, WorldModelEncoder, WorldModelView
from worldmodel.common import StageError
from worldmodel.config import compose, validate
from worldmodel.models.ddpg import DDPG, DDPGConfig
from worldmodel.models.rnn import WorldRNN
from worldmodel.models.vae import SegVAE


def world_model(seed: int = 0):
    torch.manual_seed(seed)
    vae = SegVAE(latent_dim=32)
    rnn = WorldRNN(latent_dim=32, action_dim=2, hidden=64, head="mdn", gaussians=3, residual=True)
    return vae, rnn


def test_the_default_map_is_the_identity():
    u = np.array([0.37, -0.81], np.float32)
    assert np.array_equal(ActionMap().to_env(u, 17.0), u)
    assert ActionMap.from_dict(None) == ActionMap()  # agents saved before the option existed
    m = ActionMap("brake", "grip", VehicleParams(mu=0.7))
    assert ActionMap.from_dict(m.to_dict()) == m


@pytest.mark.parametrize("mu", [1.0, 0.5])
def test_grip_scaled_steering_never_asks_for_more_than_mu_g(mu):
    params = VehicleParams(mu=mu)
    m = ActionMap(steer="grip", params=params)
    for v in np.linspace(0.5, 40.0, 80):
        for fraction in np.linspace(-1.0, 1.0, 41):
            steer = m.to_env([fraction, 0.0], v)[0]
            wheel = abs(steer) * params.max_steer
            a_lat = v * v * math.tan(wheel) / params.wheelbase  # what the kinematic model asks of the tyres
            assert a_lat <= mu * G * abs(fraction) * (1 + 1e-5) + 1e-9, (v, fraction, a_lat)
            assert np.sign(steer) == np.sign(fraction)
    # where the wheel limit does not bind, the whole range is used: u = 1 asks for exactly mu g
    steer = m.to_env([1.0, 0.0], 30.0)[0]
    a_lat = 900.0 * math.tan(steer * params.max_steer) / params.wheelbase
    assert a_lat == pytest.approx(mu * G, rel=1e-5) and steer < 0.1


def test_the_anchor_maps_zero_to_full_braking_and_covers_the_pedal():
    m = ActionMap(anchor="brake")
    assert np.array_equal(m.to_env([0.0, 0.0], 20.0), np.array([0.0, -1.0], np.float32))
    assert m.to_env([0.0, 0.5], 20.0)[1] == 0.0 and m.to_env([0.0, 1.0], 20.0)[1] == 1.0
    assert m.to_env([0.0, -0.7], 20.0)[1] == -1.0


def test_an_untrained_anchored_actor_is_straight_line_braking_exactly():
    """Zero-initialised last layer + the braking anchor: the untrained agent reproduces the baseline's rows."""
    vae, rnn = world_model()
    encoder = WorldModelEncoder(vae, rnn)
    agent = DDPG(encoder.dim, 2, DDPGConfig(actor_hidden=[32], critic_hidden=[32], actor_final_bound=0.0), seed=0)
    policy = LearnedPolicy("anchored", encoder, agent.actor, action_map=ActionMap(anchor="brake", steer="grip"))
    env = UrbanCollisionEnv(camera=True)
    entries = scenario_bank(ttcs=(0.5, 1.0), speeds=(10.0, 30.0), per_cell=1, seed=2018)[::3]
    for entry in entries:
        seen = []
        learned = rollout(env, policy, entry.spec, on_step=lambda obs, a, r, info, seen=seen: seen.append(a))
        braking = rollout(env, StraightLineBraking(), entry.spec)
        assert all(np.array_equal(a, [0.0, -1.0]) for a in seen)
        assert repr(learned.outcome) == repr(braking.outcome)
    env.close()


def test_the_lstm_is_fed_the_simulators_action():
    """Through WorldModelView, u = 0 under the anchor is the same as the action [0, -1] without it."""
    vae, rnn = world_model(1)
    spec = scenario_bank(ttcs=(1.0,), speeds=(20.0,), per_cell=1, seed=2018)[0].spec
    anchored = WorldModelView(UrbanCollisionEnv(camera=True), WorldModelEncoder(vae, rnn), ActionMap(anchor="brake"))
    plain = WorldModelView(UrbanCollisionEnv(camera=True), WorldModelEncoder(vae, rnn))
    a, _ = anchored.reset(options={"scenario": spec})
    b, _ = plain.reset(options={"scenario": spec})
    for _ in range(8):
        np.testing.assert_array_equal(a, b)
        a = anchored.step(np.zeros(2, np.float32))[0]
        b = plain.step(np.array([0.0, -1.0], np.float32))[0]
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("override,key", [("agent.anchor=pedal", "agent.anchor"), ("agent.steer=rate", "agent.steer")])
def test_unknown_action_options_are_named(override, key):
    with pytest.raises(StageError, match=key):
        validate(compose("train_agent", [override]))


@pytest.mark.parametrize("anchor,steer", [("none", "wheel"), ("brake", "wheel"), ("brake", "grip"), ("none", "grip")])
def test_from_env_inverts_to_env_where_it_can(anchor, steer):
    """Demonstrations become actor targets through from_env: mapping them back must give the planner's action."""
    m = ActionMap(anchor, steer, VehicleParams())
    rng = np.random.default_rng(0)
    for _ in range(200):
        speed = float(rng.uniform(1.0, 30.0))
        u = rng.uniform(-1, 1, 2).astype(np.float32)
        if anchor == "brake":
            u[1] = abs(u[1])  # below 0 the anchored pedal saturates at full braking: no inverse there
        a = m.to_env(u, speed)
        if abs(a[0]) >= 1.0:
            continue  # the wheel limit clipped the request
        np.testing.assert_allclose(m.to_env(m.from_env(a, speed), speed), a, atol=1e-5)
        np.testing.assert_allclose(m.from_env(a, speed), u, atol=1e-4)
    # the planner's hard swerve at 30 m/s asks for more than grip gives: all of it, in the swerve's direction
    if steer == "grip":
        assert m.from_env([-0.6, -1.0], 30.0)[0] == -1.0
