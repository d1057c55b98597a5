"""DQN with a trauma memory (Chae et al. 2017, "Autonomous braking system via deep reinforcement learning") and
Double DQN (van Hasselt et al. 2016, "Deep reinforcement learning with double Q-learning"; Merola et al. 2022).

One network Q(s, .) gives a value for each of ``n_actions`` discrete actions (Chae: no, weak, mid and strong
braking); the agent acts epsilon-greedily on it. A minibatch regresses Q(s, a) onto

    DQN:         y = r + gamma * (1 - terminated) * max_a' Q'(s', a')
    Double DQN:  y = r + gamma * (1 - terminated) * Q'(s', argmax_a' Q(s', a'))

where Q' is a target copy of Q refreshed every ``target_every`` updates. Taking the max of one noisy estimate
overestimates it; Double DQN lets the online network choose a' and the target network value it, so an action
whose value one network happens to overrate is not also valued by that same error.

**Trauma memory.** Collisions are rare, and they are terminal: the one transition that carries the collision
penalty is one among thousands in the replay memory, so uniform sampling replays it seldom, and one-step TD
needs it replayed many times before the penalty reaches the states that led to it. Chae keep a second, small
memory holding only collision transitions and draw ``trauma_batch`` of them into every minibatch; without it
their agent did not converge in over 2,000 episodes (their Fig. 5). Which transition is a trauma is the caller's
decision (``remember(..., trauma=True)``); every transition goes into the replay memory as well. With
``loss="sum"`` the loss is Chae's Eq. 9: the sum of squared TD errors over the replay batch plus the same sum
over the trauma batch.

Written in the spirit of CleanRL's ``dqn.py`` but as an importable module; unlike ``ddpg.DDPG`` the agent owns
its memories, because the trauma memory is part of the algorithm. A typical loop::

    agent = DQN(obs_dim, n_actions, DQNConfig(), seed=0)
    obs, _ = env.reset(seed=0)
    for step in range(total_steps):
        action = agent.act(obs, step)                      # epsilon-greedy, epsilon from the step
        next_obs, reward, terminated, truncated, info = env.step(action)
        agent.remember(obs, action, reward, next_obs, terminated, trauma=info["collision"])
        agent.update()                                     # None until warm-up is over
        obs = env.reset()[0] if terminated or truncated else next_obs

Store ``terminated`` (a true end: a crash, the hazard passed), not ``terminated or truncated``: a transition cut
by a time limit must still bootstrap from ``next_obs``.

Everything random after construction (exploration, minibatch indices) comes from one ``np.random.Generator``
whose state is part of ``state_dict()``, together with the memories, so a resumed run continues exactly where it
stopped.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .dqn_config import DQNConfig
from .replay import CircularStore

RESCALE_EPS = 1e-3  # Pohlen et al. 2018's epsilon: h grows linearly far out, so h^-1 stays finite


def squash(x: torch.Tensor) -> torch.Tensor:
    """h(x) = sign(x) (sqrt(|x| + 1) - 1) + eps x (``DQNConfig.value_rescale``)."""
    return torch.sign(x) * (torch.sqrt(torch.abs(x) + 1.0) - 1.0) + RESCALE_EPS * x


def unsquash(y: torch.Tensor) -> torch.Tensor:
    """h^-1(y), in closed form (Pohlen et al. 2018, Proposition A.2)."""
    root = (torch.sqrt(1.0 + 4.0 * RESCALE_EPS * (torch.abs(y) + 1.0 + RESCALE_EPS)) - 1.0) / (2.0 * RESCALE_EPS)
    return torch.sign(y) * (root**2 - 1.0)


def td_loss(q: torch.Tensor, target: torch.Tensor, kind: str, batch: int | None = None) -> torch.Tensor:
    """The TD loss of ``kind`` ("sum", "mse", "huber"; see DQNConfig.loss); the means divide by ``batch``
    (default: len(q)), so that a batch split in parts sums back to the whole."""
    if kind == "sum":
        return ((q - target) ** 2).sum()
    if batch is None:  # torch's own mean, so runs at trauma weight 1 reproduce earlier ones bit for bit
        return F.mse_loss(q, target) if kind == "mse" else F.smooth_l1_loss(q, target)
    reduction = F.mse_loss if kind == "mse" else F.smooth_l1_loss
    return reduction(q, target, reduction="sum") / batch


class QNetwork(nn.Module):
    """Q(s, .): an MLP from the observation to one value per action, leaky ReLU between layers."""

    def __init__(
        self, obs_dim: int, n_actions: int, hidden: Sequence[int] = (100, 70, 50, 70, 100), leaky_slope: float = 0.01
    ):
        super().__init__()
        layers: list[nn.Module] = []
        in_dim = obs_dim
        for width in hidden:
            layers += [nn.Linear(in_dim, width), nn.LeakyReLU(leaky_slope)]
            in_dim = width
        layers.append(nn.Linear(in_dim, n_actions))
        self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Returns Q with shape (batch, n_actions)."""
        return self.net(obs)


class TransitionBuffer(CircularStore):
    """The replay or the trauma memory of discrete-action transitions."""

    FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated")
    RESUME_HINT = "resume with the same buffer_size and trauma_size"

    def __init__(self, capacity: int, obs_dim: int):
        n = int(capacity)
        super().__init__(
            n,
            {
                "obs": np.zeros((n, obs_dim), dtype=np.float32),
                "actions": np.zeros(n, dtype=np.int64),  # int64: what torch's gather indexes with
                "rewards": np.zeros(n, dtype=np.float32),
                "next_obs": np.zeros((n, obs_dim), dtype=np.float32),
                "terminated": np.zeros(n, dtype=np.float32),
            },
        )

    def add(self, obs, action: int, reward: float, next_obs, terminated: bool) -> None:
        i = self.advance()
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, float(terminated)


class DQN:
    """Online and target Q-networks, their optimiser and learning-rate schedule, the replay and trauma memories,
    and the agent's own random generator."""

    def __init__(self, obs_dim: int, n_actions: int, cfg: DQNConfig, seed: int, device="cpu"):
        self.obs_dim, self.n_actions, self.cfg = int(obs_dim), int(n_actions), cfg
        self.device = torch.device(device)
        self.rng = np.random.default_rng(seed)
        self.steps = 0  # transitions remembered: the clock of epsilon and of warm-up
        self.updates = 0
        # Initialise from `seed` without consuming or resetting the global torch RNG, which the caller may use.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            shape = (obs_dim, n_actions, cfg.hidden, cfg.leaky_slope)
            self.q_network, self.target_network = QNetwork(*shape), QNetwork(*shape)
        self.target_network.load_state_dict(self.q_network.state_dict())
        self.target_network.requires_grad_(False)  # moved only by hard copies
        # built on the CPU from the seed, then moved: the same initial weights on every device
        self.q_network.to(self.device)
        self.target_network.to(self.device)

        optimizer = {"rmsprop": torch.optim.RMSprop, "adam": torch.optim.Adam}[cfg.optimizer]
        self.optimizer = optimizer(self.q_network.parameters(), lr=cfg.lr)
        ratio = 1.0 if cfg.lr_final is None else cfg.lr_final / cfg.lr
        total = cfg.total_steps
        # lr * ratio^(u / total): exactly lr_final after `total` updates, held there after.
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda u: ratio ** (min(u, total) / total))

        self.replay = TransitionBuffer(cfg.buffer_size, obs_dim)
        self.trauma = TransitionBuffer(cfg.trauma_size, obs_dim) if cfg.trauma_batch > 0 else None

    # ------------------------------------------------------------------ acting
    def epsilon(self, step: int | None = None) -> float:
        """Exploration probability at environment step ``step`` (default: transitions remembered so far)."""
        step = self.steps if step is None else step
        frac = min(max(step, 0) / self.cfg.eps_decay_steps, 1.0)
        return self.cfg.eps_start + frac * (self.cfg.eps_end - self.cfg.eps_start)

    @torch.no_grad()
    def q_values(self, obs: np.ndarray) -> np.ndarray:
        """Q(obs, .) from the online network, for one observation (n_actions,) or a batch (n, n_actions)."""
        values = self.q_network(torch.as_tensor(obs, dtype=torch.float32).to(self.device))
        return (unsquash(values) if self.cfg.value_rescale else values).cpu().numpy()

    def act(self, obs: np.ndarray, step: int | None = None, explore: bool = True) -> int:
        """A uniformly random action with probability ``epsilon(step)`` if ``explore``, else the greedy one."""
        if explore and self.rng.random() < self.epsilon(step):
            return int(self.rng.integers(self.n_actions))
        return int(np.argmax(self.q_values(obs)))

    def remember(
        self, obs, action: int, reward: float, next_obs, terminated: bool, trauma: bool = False, episode_end=None
    ) -> None:
        """Store a transition in the replay memory and, if ``trauma`` and the trauma memory is on, in that too.
        ``episode_end`` (where an episode ends: ``terminated or truncated``) is accepted for callers that pass it."""
        self.replay.add(obs, action, reward, next_obs, terminated)
        if trauma and self.trauma is not None:
            self.trauma.add(obs, action, reward, next_obs, terminated)
        self.steps += 1

    # ------------------------------------------------------------------ learning
    def trauma_weight(self, update: int | None = None) -> float:
        """The trauma batch's loss weight at update ``update`` (default: updates so far): 1, decaying exponentially
        to ``trauma_weight_final`` over ``total_steps`` updates when that is set."""
        final = self.cfg.trauma_weight_final
        if final is None:
            return 1.0
        u = self.updates if update is None else update
        progress = min(u, self.cfg.total_steps) / self.cfg.total_steps
        return float(final ** max(progress, 0.0))

    @torch.no_grad()
    def td_targets(self, reward: torch.Tensor, next_obs: torch.Tensor, terminated: torch.Tensor) -> torch.Tensor:
        """y = r + gamma (1 - terminated) Q'(s', a'), a' = argmax Q'(s', .) (DQN) or argmax Q(s', .) (Double DQN)
        (with ``value_rescale``, y = h(r + gamma (1 - terminated) h^-1(Q'(s', a'))), the networks holding h(Q))."""
        reward = torch.as_tensor(reward, dtype=torch.float32).to(self.device)
        next_obs = torch.as_tensor(next_obs, dtype=torch.float32).to(self.device)
        terminated = torch.as_tensor(terminated, dtype=torch.float32).to(self.device)
        next_q = self.target_network(next_obs)
        if self.cfg.double:
            next_action = self.q_network(next_obs).argmax(dim=1, keepdim=True)
            next_value = next_q.gather(1, next_action).squeeze(1)
        else:
            next_value = next_q.max(dim=1).values
        if self.cfg.value_rescale:  # the networks hold h(Q): back to returns, one Bellman step, and squash again
            target = squash(reward + self.cfg.gamma * (1.0 - terminated) * unsquash(next_value))
        else:
            target = reward + self.cfg.gamma * (1.0 - terminated) * next_value
        return target

    def update(self) -> dict[str, float] | None:
        """One gradient step on a replay batch plus a trauma batch; every ``target_every``-th also copies the
        online network into the target. None (and nothing changes) while warming up.

        Returns loss, q_mean (mean Q(s, a) over the batch), target_mean, trauma_in_batch, trauma_weight and lr (the
        rate this step used)."""
        cfg = self.cfg
        if self.steps < cfg.warmup_steps or len(self.replay) < cfg.batch_size:
            return None
        batch = self.replay.sample(cfg.batch_size, self.rng)
        n_trauma = 0
        if self.trauma is not None and len(self.trauma) > 0:
            # Without replacement: while few collisions are stored, one of them is not replayed several times over.
            n_trauma = min(cfg.trauma_batch, len(self.trauma))
            trauma = self.trauma.sample(n_trauma, self.rng, replace=False)
            batch = {name: torch.cat([batch[name], trauma[name]]) for name in batch}
        # drawn on the CPU from the agent's generator, then moved: the same minibatches on every device
        batch = {name: value.to(self.device, non_blocking=True) for name, value in batch.items()}

        target = self.td_targets(batch["rewards"], batch["next_obs"], batch["terminated"])
        q = self.q_network(batch["obs"]).gather(1, batch["actions"].unsqueeze(1)).squeeze(1)
        weight = self.trauma_weight()
        if weight == 1.0:
            loss = td_loss(q, target, cfg.loss)
        else:  # the replay part and the down-weighted trauma part, each over the whole batch as above
            split = len(q) - n_trauma
            loss = td_loss(q[:split], target[:split], cfg.loss, len(q)) + weight * td_loss(
                q[split:], target[split:], cfg.loss, len(q)
            )

        lr = self.optimizer.param_groups[0]["lr"]
        self.optimizer.zero_grad()
        loss.backward()
        if cfg.grad_clip is not None:
            nn.utils.clip_grad_norm_(self.q_network.parameters(), cfg.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.updates += 1
        if self.updates % cfg.target_every == 0:
            self.sync_target()
        return {
            "loss": loss.item(),
            "q_mean": q.mean().item(),
            "target_mean": target.mean().item(),
            "trauma_in_batch": float(n_trauma),
            "trauma_weight": weight,
            "lr": float(lr),
        }

    def sync_target(self) -> None:
        """Target := online network."""
        self.target_network.load_state_dict(self.q_network.state_dict())

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "q_network": self.q_network.state_dict(),
            "target_network": self.target_network.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "rng": self.rng.bit_generator.state,
            "steps": self.steps,
            "updates": self.updates,
            "replay": self.replay.state_dict(),
            "trauma": None if self.trauma is None else self.trauma.state_dict(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if (state["trauma"] is None) != (self.trauma is None):
            raise ValueError("the checkpoint and this agent disagree on whether the trauma memory is on (trauma_batch)")
        if state.get("average_network") is not None or state.get("earlier_targets") or state.get("normalized"):
            raise ValueError(
                "the checkpoint was trained with a weight-averaged greedy network, averaged targets or standardised "
                "inputs (greedy_average, target_average, normalize_obs), which this version no longer has"
            )
        self.q_network.load_state_dict(state["q_network"])
        self.target_network.load_state_dict(state["target_network"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.rng.bit_generator.state = state["rng"]
        self.steps, self.updates = int(state["steps"]), int(state["updates"])
        self.replay.load_state_dict(state["replay"])
        if self.trauma is not None:
            self.trauma.load_state_dict(state["trauma"])
