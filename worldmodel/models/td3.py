"""TD3 (Fujimoto et al. 2018, "Addressing function approximation error in actor-critic methods") as DDPG with
three changes, each its own option so that an ablation can take them one at a time:

- ``twin_critics``: two critics; the target takes the smaller of their two target values, which counters the
  overestimation of a single critic;
- ``policy_delay``: the actor and the targets move once every this many critic updates;
- ``target_noise``: mu'(s') in the target is smoothed by clipped Gaussian noise (+-0.5).

``make_agent`` builds DDPG or TD3, whichever a config's options ask for.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from .ddpg import DDPG
from .ddpg_config import DDPGConfig, td3_options


def make_agent(obs_dim: int, act_dim: int, cfg: DDPGConfig, seed: int, device="cpu") -> DDPG:
    """TD3 where ``cfg`` turns on any of its options, else DDPG."""
    kind = TD3 if td3_options(cfg) else DDPG
    return kind(obs_dim, act_dim, cfg, seed, device=device)


class TD3(DDPG):
    """DDPG with TD3's options: a second critic (``twin_critics``), a delayed actor (``policy_delay``) and target
    smoothing (``target_noise``)."""

    critic2: nn.Module | None
    critic2_target: nn.Module | None

    def _build_more_critics(self) -> None:
        twin = self.cfg.twin_critics
        self.critic2 = self._critic() if twin else None
        self.critic2_target = self._critic() if twin else None

    def _pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        pairs = super()._pairs()
        return pairs + [(self.critic2, self.critic2_target)] if self.critic2 is not None else pairs

    def _critic_parameters(self) -> list:
        return super()._critic_parameters() + (list(self.critic2.parameters()) if self.critic2 is not None else [])

    def target_action(self, next_obs: torch.Tensor) -> torch.Tensor:
        next_action = self.actor_target(next_obs)
        if self.cfg.target_noise > 0:
            # drawn on the CPU generator, then moved: the same noise on every device
            noise = torch.randn(next_action.shape, generator=self.torch_rng).to(self.device) * self.cfg.target_noise
            next_action = (next_action + noise.clamp(-0.5, 0.5)).clamp(-1.0, 1.0)
        return next_action

    def target_q(self, next_obs: torch.Tensor, next_action: torch.Tensor) -> torch.Tensor:
        next_q = self.critic_target(next_obs, next_action)
        if self.critic2_target is not None:
            next_q = torch.minimum(next_q, self.critic2_target(next_obs, next_action))
        return next_q

    def critic_loss(self, batch: Mapping[str, torch.Tensor], q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        loss = F.mse_loss(q, target)
        if self.critic2 is not None:
            loss = loss + F.mse_loss(self.critic2(batch["obs"], batch["actions"]), target)
        return loss

    def actor_due(self) -> bool:
        return self.updates % self.cfg.policy_delay == 0

    def _more_critics_state(self) -> dict[str, Any]:
        if self.critic2 is None:
            return {}
        return {"critic2": self.critic2.state_dict(), "critic2_target": self.critic2_target.state_dict()}

    def _load_more_critics(self, state: Mapping[str, Any]) -> None:
        if self.critic2 is not None:
            self.critic2.load_state_dict(state["critic2"])
            self.critic2_target.load_state_dict(state["critic2_target"])
