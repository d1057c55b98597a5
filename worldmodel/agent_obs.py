"""The agent's view of the live env: [z_t, zhat_{t+1}] (optionally with speed), as in the paper's phase 3.

* z_t is the VAE's mean mu(obs_t) for the current frame (no sampling at decision time).
* zhat_{t+1} is the LSTM's point prediction after feeding (z_t, a_{t-1}). The current action a_t is not known
  yet when the agent decides, so the previous action is held; the LSTM state is advanced with that same pair.
  This is one LSTM step per decision (the alternative, predicting with a_{t-1} and then re-stepping with a_t,
  would double the cost for a state that differs only in one step's action). a_{-1} = [0, 0].

``WorldModelEncoder`` holds that recurrent state; ``WorldModelView`` wraps a gymnasium env with it (training),
and ``LearnedPolicy`` drives an actor with it behind the scripted-policy interface (evaluation).
"""
from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import torch

# Toggling oneDNN below makes torch mention Intel-GPU TF32 support, which has nothing to do with CPU inference.
warnings.filterwarnings("ignore", message="TF32 acceleration on top of oneDNN")


class WorldModelEncoder:
    def __init__(self, vae, rnn, use_speed: bool = False):
        self.vae, self.rnn, self.use_speed = vae.eval(), rnn.eval(), bool(use_speed)
        self.latent_dim = vae.latent_dim
        self.dim = 2 * self.latent_dim + (1 if use_speed else 0)
        self.reset()

    def reset(self) -> None:
        self.state = self.rnn.initial_state(1)
        self.prev_action = torch.zeros(1, 2)

    def note_action(self, action) -> None:
        self.prev_action = torch.as_tensor(np.asarray(action, dtype=np.float32)).reshape(1, 2)

    @torch.inference_mode()
    def encode(self, obs: dict) -> np.ndarray:
        seg = torch.from_numpy(np.ascontiguousarray(obs["seg"])).unsqueeze(0)
        # oneDNN re-lays out the conv weights on every batch-1 call; the plain kernels are ~2x faster here.
        with torch.backends.mkldnn.flags(enabled=False):
            z, _ = self.vae.encode(seg)
        out, self.state = self.rnn.step(z, self.prev_action, self.state)
        zhat = self.rnn.predict(out)
        parts = [z, zhat]
        if self.use_speed:
            parts.append(torch.as_tensor(obs["speed"], dtype=torch.float32).reshape(1, 1) / 30.0)
        return torch.cat(parts, dim=1)[0].numpy().astype(np.float32)


class WorldModelView(gym.Wrapper):
    """A gymnasium env whose observation is the agent input vector."""

    def __init__(self, env: gym.Env, encoder: WorldModelEncoder):
        super().__init__(env)
        self.encoder = encoder
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (encoder.dim,), np.float32)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.encoder.reset()
        return self.encoder.encode(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.encoder.note_action(action)
        return self.encoder.encode(obs), reward, terminated, truncated, info


class LearnedPolicy:
    """A trained actor behind the scripted-policy interface: ``reset(seed)``, ``act(obs, info)``."""

    def __init__(self, name: str, encoder: WorldModelEncoder, actor):
        self.name, self.encoder, self.actor = name, encoder, actor.eval()

    def reset(self, seed=None) -> None:
        self.encoder.reset()

    @torch.inference_mode()
    def act(self, obs, info) -> np.ndarray:
        x = torch.from_numpy(self.encoder.encode(obs)).unsqueeze(0)
        action = self.actor(x)[0].numpy().astype(np.float32)
        self.encoder.note_action(action)
        return action
