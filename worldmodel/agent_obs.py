"""The agent's view of the live env: [z_t, zhat_{t+1}] (optionally with speed), as in the paper's phase 3.

With ``agent.frame_view`` the hazard profiles of the current and previous frame (``envs/views.py``) follow.

* z_t is the VAE's mean mu(obs_t) for the current frame (no sampling at decision time).
* zhat_{t+1} is the LSTM's point prediction after feeding (z_t, a_{t-1}). The current action a_t is not known
  yet when the agent decides, so the previous action is held; the LSTM state is advanced with that same pair.
  This is one LSTM step per decision (the alternative, predicting with a_{t-1} and then re-stepping with a_t,
  would double the cost for a state that differs only in one step's action). a_{-1} = [0, 0].

``WorldModelEncoder`` holds that recurrent state; ``WorldModelView`` wraps a gymnasium env with it (training),
and ``LearnedPolicy`` drives an actor with it behind the scripted-policy interface (evaluation).

Both run every frame through the batch-1 decision path of ``models/fast_decision.py``: the fast path where its
self-test passes on this torch build, else the module path with the same numbers (``path`` forces one).
Training keeps using the modules themselves.

``PrivilegedEncoder`` puts the simulator's true state (``obs=privileged``, ``envs/privileged.py``) behind the
encoder's interface, so that the paper's DDPG acts on it through the same view and policy, without the camera.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from envs.views import HazardView

from .action_map import ActionMap
from .models.fast_decision import actor_path, decision_path
from .models.vae import IMAGE_SIZE


class WorldModelEncoder:
    """The recurrent agent input: VAE + LSTM behind one decision path (``path``: auto | fast | module)."""

    def __init__(self, vae, rnn, use_speed: bool = False, path: str = "auto", frame_view: bool = False):
        self.vae, self.rnn, self.use_speed = vae.eval(), rnn.eval(), bool(use_speed)
        self.latent_dim = vae.latent_dim
        self.decision = decision_path(self.vae, self.rnn, self.use_speed, path)
        self.path = self.decision.path
        # the hazard profiles of the raw frame (envs/views.py), appended after the world model's part
        self.frame_view = HazardView(IMAGE_SIZE) if frame_view else None
        self.dim = self.decision.dim + (self.frame_view.dim if self.frame_view else 0)
        self._out = torch.zeros(1, self.dim, device=next(vae.parameters()).device)

    def reset(self) -> None:
        self.decision.reset()
        if self.frame_view is not None:
            self.frame_view.reset()

    def note_action(self, action) -> None:
        self.decision.note_action(action)

    @property
    def state(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.decision.state

    def encode_tensor(self, obs: dict) -> torch.Tensor:
        """The agent input as a ``(1, dim)`` tensor that the next call overwrites."""
        x = self.decision.encode(obs["seg"], obs.get("speed") if self.use_speed else None)
        if self.frame_view is None:
            return x
        d = self.decision.dim
        self._out[:, :d] = x
        self._out[0, d:] = torch.from_numpy(self.frame_view(np.asarray(obs["seg"])))
        return self._out

    def encode(self, obs: dict) -> np.ndarray:
        # inference_mode is not needed (nothing here requires grad) but measured ~15 us faster per decision
        with torch.inference_mode():
            return self.encode_tensor(obs)[0].cpu().numpy().copy()


class PrivilegedEncoder:
    """``obs=privileged``: the true state of the bound env (``envs/privileged.py``) instead of the camera's
    [z_t, zhat_{t+1}], behind ``WorldModelEncoder``'s interface. No world model and no camera: ``bind(env)`` (at
    construction for training, after each reset in evaluation) hands it the simulator it reads; ``obs`` is ignored."""

    needs_camera = False

    def __init__(self, env=None, device=None):
        from envs.privileged import PRIVILEGED_DIM

        self.dim = PRIVILEGED_DIM
        self.env = None
        self._out = torch.zeros(1, self.dim, device=device or "cpu")
        if env is not None:
            self.bind(env)

    def bind(self, env) -> None:
        self.env = getattr(env, "unwrapped", env)

    def reset(self) -> None:
        pass

    def note_action(self, action) -> None:
        pass

    def encode(self, obs=None) -> np.ndarray:
        from envs.privileged import privileged_state

        if self.env is None:
            raise RuntimeError("the privileged observation reads the simulator: bind(env) first")
        return privileged_state(self.env)

    def encode_tensor(self, obs=None) -> torch.Tensor:
        """The agent input as a ``(1, dim)`` tensor that the next call overwrites."""
        self._out[0] = torch.from_numpy(self.encode(obs))
        return self._out


def encode_episode(encoder: WorldModelEncoder, seg: np.ndarray, speed: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The agent inputs a live run would have produced for a recorded episode: ``(T, dim)`` from its T frames and
    speeds and the simulator's actions (``actions[t]`` taken after frame t), fed as ``WorldModelView`` feeds them."""
    encoder.reset()
    out = np.empty((len(seg), encoder.dim), np.float32)
    for t in range(len(seg)):
        out[t] = encoder.encode({"seg": seg[t], "speed": speed[t : t + 1]})
        if t + 1 < len(seg):
            encoder.note_action(actions[t])
    return out


class WorldModelView(gym.Wrapper):
    """A gymnasium env whose observation is the agent input vector and whose action is the actor's output ``u``,
    mapped to the simulator's action by ``action_map`` (``worldmodel/action_map.py``; the identity by default)."""

    def __init__(self, env: gym.Env, encoder: WorldModelEncoder, action_map: ActionMap | None = None):
        super().__init__(env)
        self.encoder = encoder
        self.action_map = action_map or ActionMap()
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (encoder.dim,), np.float32)
        self._speed = 0.0

    @property
    def speed(self) -> float:
        """The ego speed of the last observation (m/s): what grip-scaled steering reads."""
        return self._speed

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.encoder.reset()
        self._speed = float(obs["speed"][0])
        return self.encoder.encode(obs), info

    def step(self, action):
        action = self.action_map.to_env(action, self._speed)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.encoder.note_action(action)  # the LSTM was trained on the simulator's actions
        self._speed = float(obs["speed"][0])
        return self.encoder.encode(obs), reward, terminated, truncated, info


class LearnedPolicy:
    """A trained actor behind the scripted-policy interface: ``reset(seed)``, ``act(obs, info)``."""

    def __init__(
        self, name: str, encoder: WorldModelEncoder, actor, path: str = "auto", action_map: ActionMap | None = None
    ):
        self.name, self.encoder, self.actor = name, encoder, actor.eval()
        self.decide = actor_path(self.actor, path)
        self.action_map = action_map or ActionMap()

    @property
    def needs_camera(self) -> bool:
        """Whether it acts on the camera (the world model's view) or on the true state (``PrivilegedEncoder``)."""
        return getattr(self.encoder, "needs_camera", True)

    def reset(self, seed=None) -> None:
        self.encoder.reset()

    def bind(self, env) -> None:
        """The env of the episode just reset, for an encoder that reads the true state (evaluation calls it)."""
        bind = getattr(self.encoder, "bind", None)
        if bind is not None:
            bind(env)

    def act(self, obs, info) -> np.ndarray:
        with torch.inference_mode():
            x = self.encoder.encode_tensor(obs)
            a = self.decide(x)
            action = a[0].cpu().numpy().astype(np.float32)  # astype copies: the buffer is reused
        if not self.action_map.identity:
            action = self.action_map.to_env(action, float(np.asarray(obs["speed"]).reshape(-1)[0]))
        self.encoder.note_action(action)
        return action
