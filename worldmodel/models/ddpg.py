"""DDPG (Lillicrap et al. 2015, "Continuous control with deep reinforcement learning").

A deterministic actor mu(s) in [-1, 1]^act_dim and a critic Q(s, a), each with a slowly tracking target
copy. The critic regresses onto

    y = r + gamma * (1 - terminated) * Q'(s', mu'(s'))

and the actor ascends Q(s, mu(s)). Written in the spirit of CleanRL's ``ddpg_continuous_action.py`` but as
an importable module: the project trains it through ``learners/ddpg.py:DDPGLearner`` in the one training loop
(``learners/loop.py``), which adds warm-up, n-step returns and demonstrations. Bare, a loop reads::

    agent = DDPG(obs_dim, act_dim, DDPGConfig(), seed=0)   # the project passes its typed `agent` config section
    buffer = ReplayBuffer(agent.cfg.buffer_size, obs_dim, act_dim)
    for step in range(total_steps):
        action = agent.random_action() if step < agent.cfg.warmup_steps else agent.act(obs, explore=True)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        buffer.add(obs, action, reward, next_obs, terminated)   # not `terminated or truncated`
        if step >= agent.cfg.warmup_steps:
            agent.update(buffer.sample(agent.cfg.batch_size, agent.rng))

Everything random after construction (exploration noise, warm-up actions, minibatch indices when the caller
passes ``agent.rng``) comes from one ``np.random.Generator`` whose state is part of ``state_dict()``, so a
resumed run continues exactly where it stopped.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .ddpg_config import DDPGConfig, td3_options
from .replay import CircularStore


def mlp(in_dim: int, hidden: Sequence[int], out_dim: int) -> nn.Sequential:
    """Linear layers with ReLU between them; the last layer is linear so the caller picks the squashing."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_dim, width), nn.ReLU()]
        in_dim = width
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


def init_final_layer(layer: nn.Linear, bound: float = 3e-3) -> None:
    # Lillicrap sec. 7: a near-zero final layer makes initial actions and Q-values close to zero, so the
    # first updates are not dominated by an arbitrary random policy or value estimate.
    nn.init.uniform_(layer.weight, -bound, bound)
    nn.init.uniform_(layer.bias, -bound, bound)


class LidarEncoder(nn.Module):
    """Kim et al. 2020's LIDAR front end: ``scans`` scans of ``rays`` ranges (the observation's first scans x rays
    numbers) through Conv1d(scans -> 16, k5, circular padding, as the angle wraps around) and Conv1d(16 -> 32, k3,
    stride 2), ReLU after each, flattened and joined by the observation's remaining numbers."""

    def __init__(self, obs_dim: int, scans: int, rays: int):
        super().__init__()
        self.scans, self.rays = int(scans), int(rays)
        self.extra = int(obs_dim) - self.scans * self.rays
        if self.extra < 0:
            raise ValueError(f"an observation of {obs_dim} numbers cannot hold {scans} scans of {rays} rays")
        self.conv = nn.Sequential(
            nn.Conv1d(self.scans, 16, 5, padding=2, padding_mode="circular"),
            nn.ReLU(),
            nn.Conv1d(16, 32, 3, stride=2),
            nn.ReLU(),
            nn.Flatten(),
        )
        self.out_dim = 32 * ((self.rays - 3) // 2 + 1) + self.extra

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        n = self.scans * self.rays
        scans = obs[..., :n].reshape(-1, self.scans, self.rays)
        features = self.conv(scans).reshape(*obs.shape[:-1], -1)
        return torch.cat([features, obs[..., n:]], dim=-1)


def front_end(obs_dim: int, lidar_scans: int = 0, lidar_rays: int = 36) -> tuple[nn.Module, int]:
    """(module, its output width): the LIDAR encoder, or the observation as it is."""
    if lidar_scans:
        encoder = LidarEncoder(obs_dim, lidar_scans, lidar_rays)
        return encoder, encoder.out_dim
    return nn.Identity(), obs_dim


class Actor(nn.Module):
    """Deterministic policy mu(s) with actions in [-1, 1]^act_dim."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (400, 300),
        final_bound: float = 3e-3,
        lidar_scans: int = 0,
        lidar_rays: int = 36,
    ):
        super().__init__()
        self.encode, width = front_end(obs_dim, lidar_scans, lidar_rays)
        self.net = mlp(width, hidden, act_dim)
        init_final_layer(self.net[-1], final_bound)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(self.encode(obs)))


class Critic(nn.Module):
    """Q(s, a). ``action_layer`` 0: the action joins the observation at the input (CleanRL); 1: it joins the
    first hidden layer's output (Lillicrap), where it is 2 of ~400 inputs rather than 2 of ~258."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (400, 300),
        action_layer: int = 0,
        lidar_scans: int = 0,
        lidar_rays: int = 36,
    ):
        super().__init__()
        self.action_layer = int(action_layer)
        self.encode, obs_dim = front_end(obs_dim, lidar_scans, lidar_rays)
        if self.action_layer == 0:
            self.net = mlp(obs_dim + act_dim, hidden, 1)
        else:
            self.first = nn.Sequential(nn.Linear(obs_dim, hidden[0]), nn.ReLU())
            self.net = mlp(hidden[0] + act_dim, hidden[1:], 1)
        init_final_layer(self.net[-1])

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Returns Q with shape (batch,)."""
        obs = self.encode(obs)
        if self.action_layer:
            obs = self.first(obs)
        return self.net(torch.cat([obs, action], dim=-1)).squeeze(-1)


class NStepWindow:
    """Turns one-step transitions into n-step ones, in order, within one episode.

    ``push`` returns the transitions that are complete; ``flush`` (at the episode's end) the rest, each with as
    many steps as remain. A transition is (obs, action, return, next_obs, terminated, steps): return is
    r_t + g r_(t+1) + ... + g^(k-1) r_(t+k-1) and next_obs is the observation k steps later, so the target is
    return + g^k (1 - terminated) Q'(next_obs). A termination inside the window ends it: nothing after it counts.
    """

    def __init__(self, n: int, gamma: float):
        self.n, self.gamma = int(n), float(gamma)
        self.pending: list[tuple] = []

    def _emit(self, k: int) -> tuple:
        obs, action = self.pending[0][0], self.pending[0][1]
        ret = sum(self.gamma**j * self.pending[j][2] for j in range(k))
        _, _, _, next_obs, terminated = self.pending[k - 1]
        self.pending.pop(0)
        return obs, action, ret, next_obs, terminated, k

    def push(self, obs, action, reward: float, next_obs, terminated: bool) -> list[tuple]:
        self.pending.append((obs, action, float(reward), next_obs, bool(terminated)))
        if terminated:
            return self.flush()
        return [self._emit(self.n)] if len(self.pending) == self.n else []

    def flush(self) -> list[tuple]:
        out = []
        while self.pending:
            out.append(self._emit(len(self.pending)))
        return out

    def store(self, buffer, obs, action, reward: float, next_obs, terminated: bool, truncated: bool) -> None:
        """Push one step and add what it completes to ``buffer``: at a truncation, every pending transition,
        whose returns are cut there (bootstrapped from the last observation)."""
        for transition in self.push(obs, action, reward, next_obs, terminated):
            buffer.add(*transition)
        if truncated and not terminated:
            for transition in self.flush():
                buffer.add(*transition)

    def state_dict(self) -> list[tuple]:
        """The transitions still waiting for their n steps: a checkpoint inside an episode keeps them."""
        return list(self.pending)

    def load_state_dict(self, pending: list[tuple]) -> None:
        self.pending = list(pending)


class ReplayBuffer(CircularStore):
    """The DDPG replay memory: continuous actions, and ``steps``, the k of an n-step transition (the target
    discounts its bootstrap by gamma^k). ``terminated`` is 1.0 only for true terminal states (a crash with a car or a
    static object, or leaving the scene; stopping does not end an episode)."""

    FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated", "steps")
    KIND = "replay buffer"
    RESUME_HINT = "resume with the same agent.ddpg.buffer_size"

    def __init__(self, capacity: int, obs_dim: int, act_dim: int):
        n = int(capacity)
        super().__init__(
            n,
            {
                "obs": np.zeros((n, obs_dim), dtype=np.float32),
                "actions": np.zeros((n, act_dim), dtype=np.float32),
                "rewards": np.zeros(n, dtype=np.float32),
                "next_obs": np.zeros((n, obs_dim), dtype=np.float32),
                "terminated": np.zeros(n, dtype=np.float32),
                "steps": np.ones(n, dtype=np.float32),  # checkpoints from before n-step returns: all one-step
            },
        )

    def add(self, obs, action, reward: float, next_obs, terminated: bool, steps: int = 1) -> None:
        i = self.advance()
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminated[i], self.steps[i] = next_obs, float(terminated), steps


class DDPG:
    """Lillicrap's DDPG: an actor, a critic, their targets and optimisers, and the agent's own random generator.

    ``n_step`` is read from each transition's ``steps``; ``bc_weight`` adds behaviour cloning on the samples a
    batch marks as demonstrations (``batch["demo"]``), Q-filtered if asked. TD3's options (``twin_critics``,
    ``policy_delay``, ``target_noise``) belong to ``worldmodel.models.td3.TD3``, which extends this class;
    ``td3.make_agent`` builds whichever of the two a config asks for.
    """

    def __init__(self, obs_dim: int, act_dim: int, cfg: DDPGConfig, seed: int, device="cpu"):
        if type(self) is DDPG and td3_options(cfg):
            raise ValueError(
                f"{', '.join(td3_options(cfg))}: TD3's options; build worldmodel.models.td3.TD3, or let "
                "worldmodel.models.td3.make_agent choose"
            )
        self.obs_dim, self.act_dim, self.cfg = int(obs_dim), int(act_dim), cfg
        self.device = torch.device(device)
        self.rng = np.random.default_rng(seed)
        self.updates = 0
        # Initialise the networks from `seed` without consuming or resetting the global torch RNG,
        # which the caller may be using for something else.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.actor = self._actor()
            self.critic = self._critic()
            self.actor_target = self._actor()
            self.critic_target = self._critic()
            self._build_more_critics()
            # the generator of TD3's target-smoothing noise; every agent saves one, so that checkpoints share a shape
            self.torch_rng = torch.Generator().manual_seed(int(seed))
        for online, target in self._pairs():
            target.load_state_dict(online.state_dict())
            target.requires_grad_(False)  # targets are only ever read under no_grad and moved by soft_update
        # built on the CPU from the seed, then moved: the same initial weights on every device
        for pair in self._pairs():
            for net in pair:
                net.to(self.device)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.critic_optimizer = torch.optim.Adam(self._critic_parameters(), lr=cfg.critic_lr)

    def _actor(self) -> Actor:
        cfg = self.cfg
        return Actor(self.obs_dim, self.act_dim, cfg.actor_hidden, cfg.actor_final_bound, **self._lidar())

    def _critic(self) -> Critic:
        cfg = self.cfg
        return Critic(self.obs_dim, self.act_dim, cfg.critic_hidden, cfg.critic_action_layer, **self._lidar())

    def _lidar(self) -> dict:
        return {"lidar_scans": self.cfg.lidar_scans, "lidar_rays": self.cfg.lidar_rays}

    def _build_more_critics(self) -> None:
        """TD3 builds its second critic and target here, drawing from the seeded generator after the first pair."""

    def _pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        """(online, target) for the actor and every critic."""
        return [(self.actor, self.actor_target), (self.critic, self.critic_target)]

    def _critic_parameters(self) -> list:
        return list(self.critic.parameters())

    def _targets(self):
        return [target for _, target in self._pairs()]

    # ------------------------------------------------------------------ acting
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """mu(obs), plus Gaussian noise if ``explore``; float32 in [-1, 1]. ``obs`` may be one observation
        (obs_dim,) or a batch (n, obs_dim)."""
        with torch.inference_mode():
            # as_tensor shares memory with a float32 array, so acting allocates nothing the size of the input.
            action = self.actor(torch.as_tensor(obs, dtype=torch.float32).to(self.device)).cpu().numpy()
        if explore:
            action = action + self.rng.normal(0.0, self.cfg.exploration_noise, size=action.shape)
        return np.clip(action, -1.0, 1.0).astype(np.float32, copy=False)

    def random_action(self) -> np.ndarray:
        """Uniform in [-1, 1]^act_dim, for the warm-up phase."""
        return self.rng.uniform(-1.0, 1.0, size=self.act_dim).astype(np.float32)

    # ------------------------------------------------------------------ learning
    @torch.no_grad()
    def td_target(self, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """y = R + g^k (1 - terminated) Q'(s', mu'(s')) from the target networks; R and k are the transition's
        (n-step) return and length, k = 1 for a one-step transition (TD3 changes ``target_action`` and
        ``target_q``).

        Only true terminations stop the bootstrap; a time-limit truncation must be stored with terminated=0.
        """
        next_obs = batch["next_obs"]
        next_q = self.target_q(next_obs, self.target_action(next_obs))
        steps = batch.get("steps")
        discount = self.cfg.gamma if steps is None else self.cfg.gamma**steps
        return batch["rewards"] + discount * (1.0 - batch["terminated"]) * next_q

    def target_action(self, next_obs: torch.Tensor) -> torch.Tensor:
        """mu'(s'), the action the target bootstraps from."""
        return self.actor_target(next_obs)

    def target_q(self, next_obs: torch.Tensor, next_action: torch.Tensor) -> torch.Tensor:
        """Q'(s', a')."""
        return self.critic_target(next_obs, next_action)

    def critic_loss(self, batch: Mapping[str, torch.Tensor], q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The critic's regression onto the target; ``q`` is Q(s, a) on the batch."""
        return F.mse_loss(q, target)

    def actor_due(self) -> bool:
        """Whether this update moves the actor and the targets too (DDPG: every one)."""
        return True

    def bc_loss(self, batch: Mapping[str, torch.Tensor], policy_action: torch.Tensor, q_policy: torch.Tensor):
        """Behaviour cloning on the batch's demonstration samples: mean over them of keep * |mu(s) - a|^2, where
        keep is 1, or with the Q-filter 1 only where Q(s, a_demo) > Q(s, mu(s)). Returns (loss, share kept)."""
        demo = batch["demo"]
        n_demo = demo.sum()
        if n_demo == 0:
            return policy_action.sum() * 0.0, 0.0
        keep = demo
        if self.cfg.q_filter:
            with torch.no_grad():
                keep = demo * (self.critic(batch["obs"], batch["actions"]) > q_policy.detach()).float()
        error = ((policy_action - batch["actions"]) ** 2).sum(-1)
        return (keep * error).sum() / n_demo, float(keep.sum() / n_demo)

    def update(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """One gradient step on the critic(s); then, when ``actor_due`` (every call; TD3: every
        ``policy_delay``-th), one on the actor and a soft update of the targets. The batch may be on the CPU: it is
        moved to the agent's device."""
        batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
        target = self.td_target(batch)
        q = self.critic(batch["obs"], batch["actions"])
        critic_loss = self.critic_loss(batch, q, target)
        self.critic_optimizer.zero_grad()
        critic_loss.backward()
        self.critic_optimizer.step()
        self.updates += 1
        out = {"critic_loss": critic_loss.item(), "q_mean": q.mean().item()}
        if not self.actor_due():
            return out

        # The actor is judged by the critic just updated (as in Lillicrap's Algorithm 1). The gradients this
        # leaves on the critic's parameters are discarded by the critic's zero_grad on the next update.
        policy_action = self.actor(batch["obs"])
        q_policy = self.critic(batch["obs"], policy_action)
        actor_loss = -q_policy.mean()
        if self.cfg.bc_weight > 0 and "demo" in batch:
            bc, kept = self.bc_loss(batch, policy_action, q_policy)
            actor_loss = actor_loss + self.cfg.bc_weight * bc
            out.update(bc_loss=bc.item(), bc_kept=kept)
        self.actor_optimizer.zero_grad()
        actor_loss.backward()
        self.actor_optimizer.step()

        self.soft_update()
        out["actor_loss"] = actor_loss.item()
        return out

    def clone(self, obs: torch.Tensor, actions: torch.Tensor, weights: torch.Tensor | None = None) -> float:
        """One supervised step of the actor towards ``actions`` (behaviour-cloning pre-training), each sample's squared
        error weighted by ``weights`` (None: all alike); returns the loss."""
        if getattr(self, "_clone_optimizer", None) is None:
            self._new_clone_optimizer()
        obs, actions = obs.to(self.device), actions.to(self.device)
        weights = None if weights is None else weights.to(self.device)
        squared = ((self.actor(obs) - actions) ** 2).sum(-1)
        loss = squared.mean() if weights is None else (weights * squared).sum() / weights.sum()
        self._clone_optimizer.zero_grad()
        loss.backward()
        self._clone_optimizer.step()
        return loss.item()

    def _new_clone_optimizer(self) -> torch.optim.Optimizer:
        # its own optimiser: pre-training ends before RL starts, and the actor's Adam state stays fresh
        self._clone_optimizer = torch.optim.AdamW(
            self.actor.parameters(), lr=self.cfg.bc_lr, weight_decay=self.cfg.bc_weight_decay
        )
        return self._clone_optimizer

    def sync_targets(self) -> None:
        """Targets := online networks (after pre-training, so the targets start from what was learnt)."""
        for online, target in self._pairs():
            target.load_state_dict(online.state_dict())

    @torch.no_grad()
    def soft_update(self) -> None:
        """target <- (1 - tau) * target + tau * online, for the actor and every critic."""
        for online, target in self._pairs():
            for p, tp in zip(online.parameters(), target.parameters()):
                tp.lerp_(p, self.cfg.tau)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        state = {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "rng": self.rng.bit_generator.state,
            "torch_rng": self.torch_rng.get_state(),
            "updates": self.updates,
        }
        state.update(self._more_critics_state())
        if getattr(self, "_clone_optimizer", None) is not None:  # cloning rounds share it: a resumed round goes on
            state["clone_optimizer"] = self._clone_optimizer.state_dict()
        return state

    def _more_critics_state(self) -> dict[str, Any]:
        return {}

    def _load_more_critics(self, state: Mapping[str, Any]) -> None:
        """TD3 loads its second critic and target here."""

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.actor_target.load_state_dict(state["actor_target"])
        self.critic_target.load_state_dict(state["critic_target"])
        self._load_more_critics(state)
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.rng.bit_generator.state = state["rng"]
        if "torch_rng" in state:  # absent from checkpoints made before TD3's options
            self.torch_rng.set_state(state["torch_rng"])
            self.updates = int(state["updates"])
        if "clone_optimizer" in state:
            self._new_clone_optimizer().load_state_dict(state["clone_optimizer"])
