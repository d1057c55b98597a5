"""DDPG's hyperparameters, apart from the learner so that reading a config never imports torch: ``DDPGSettings``
(the config section ``agent.ddpg``) and ``DDPGConfig`` (those with the LIDAR observation's shape: what a DDPG is
built with, and what its checkpoint records)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..common import Checked, ConfigValueError, positive_fields


@dataclass
class DDPGSettings(Checked):
    """DDPG's hyperparameters: the schema of the config section ``agent.ddpg``, which the paper's DDPG (and TD3)
    and Kim et al.'s LIDAR DDPG read. Defaults are Lillicrap's where the paper is silent."""

    actor_hidden: list[int] = field(default_factory=lambda: [400, 300])
    """widths of the actor's hidden layers (Lillicrap: 400, 300)"""
    critic_hidden: list[int] = field(default_factory=lambda: [400, 300])
    """widths of the critic's hidden layers (Lillicrap: 400, 300)"""
    actor_lr: float = 1e-4
    """Adam learning rate of the actor (Lillicrap: 1e-4)"""
    critic_lr: float = 1e-3
    """Adam learning rate of the critic (Lillicrap: 1e-3); faster than the actor so Q stays a usable guide"""
    gamma: float = 0.99
    """discount factor (Lillicrap: 0.99)"""
    tau: float = 0.005
    """target-network tracking rate per update. Lillicrap use 0.001 over ~1M steps; our runs are 20-60k steps,
    so targets must follow faster (0.005 is the TD3/CleanRL value)"""
    batch_size: int = 64
    """minibatch size per update (Lillicrap: 64)"""
    buffer_size: int = 100_000
    """replay capacity in transitions. Lillicrap use 1e6; ours holds every transition of a `paper` run"""
    exploration_noise: float = 0.2
    """std of the Gaussian noise added to actions (action units, actions in [-1, 1]). Lillicrap use
    Ornstein-Uhlenbeck noise with sigma 0.2; uncorrelated Gaussian noise works as well (Fujimoto et al. 2018)
    and carries no state that a resumed run would have to restore"""
    warmup_steps: int = 1000
    """environment steps with uniform random actions before the first update, so early minibatches are not
    all drawn from the same few transitions"""

    actor_final_bound: float = 3e-3
    """the actor's last layer starts uniform in +-bound (Lillicrap: 3e-3, so first actions are near 0). 0 makes the
    untrained actor output exactly 0: with ``agent.anchor=brake``, exactly straight-line braking"""

    # ---- learner options (all off by default, which is Lillicrap's DDPG above)
    n_step: int = 1
    """n-step returns: the critic regresses onto r_t + ... + g^(k-1) r_(t+k-1) + g^k Q'(s_(t+k), mu'(s_(t+k))), k <= n
    (fewer at an episode's end). Sparse terminal rewards then reach the decision that caused them n times faster"""
    twin_critics: bool = False
    """TD3 (Fujimoto et al. 2018): two critics, the target takes the smaller of their two target values, which
    counters the overestimation of a single critic"""
    policy_delay: int = 1
    """update the actor (and the targets) once every this many critic updates (TD3: 2)"""
    target_noise: float = 0.0
    """TD3's target policy smoothing: Gaussian noise of this std on mu'(s') in the target, clipped to +-0.5"""
    critic_action_layer: int = 0
    """where the action enters the critic: 0 = with the observation at the input (CleanRL), 1 = at the second
    layer (Lillicrap), so 2 action numbers do not drown among 256 latent ones"""
    bc_weight: float = 0.0
    """behaviour cloning in the actor's loss on demonstration samples: + bc_weight * |mu(s) - a_demo|^2
    (Nair et al. 2018). 0 = off"""
    bc_lr: float = 1e-3
    """Adam learning rate of behaviour-cloning pre-training (a supervised problem: faster than actor_lr)"""
    bc_weight_decay: float = 0.0
    """AdamW weight decay of behaviour-cloning pre-training: a few hundred demonstrations overfit a 400-300 actor"""
    q_filter: bool = True
    """apply the cloning term only where the critic rates the demonstrated action above the actor's own (Nair et
    al.'s Q-filter), so that a demonstrator that swerves left here and right there does not teach a half-swerve"""

    def problems(self):
        yield from positive_fields(self, "batch_size", "buffer_size", "actor_lr", "critic_lr", "bc_lr")
        for key in ("gamma", "tau"):
            if not 0 < getattr(self, key) <= 1:
                yield ConfigValueError(key, getattr(self, key), "it must be in (0, 1]")
        yield from positive_fields(self, "n_step", "policy_delay")
        if self.critic_action_layer not in (0, 1):
            yield ConfigValueError("critic_action_layer", self.critic_action_layer, "it must be 0 or 1")
        non_negative = ("warmup_steps", "exploration_noise", "actor_final_bound", "target_noise", "bc_weight")
        for key in (*non_negative, "bc_weight_decay"):
            if getattr(self, key) < 0:
                yield ConfigValueError(key, getattr(self, key), "it must be >= 0")
        for key in ("actor_hidden", "critic_hidden"):
            if not all(isinstance(w, int) and w > 0 for w in getattr(self, key)):
                yield ConfigValueError(key, list(getattr(self, key)), "layer widths must be positive integers")


@dataclass
class DDPGConfig(DDPGSettings):
    """What a DDPG is built with: its hyperparameters (``DDPGSettings``, ``agent.ddpg``) and the shape of the LIDAR
    observation it reads, which are the agent section's (``agent.lidar_scans``, ``agent.lidar_rays``) because
    the LIDAR chooser reads them too."""

    lidar_scans: int = 0
    """0: the observation goes straight into the networks. k > 0: its first k x ``lidar_rays`` numbers are k LIDAR
    scans (oldest first), which actor and critic each read through Kim et al.'s 1-D convolutions over the angle
    (``LidarEncoder``); the rest (previous action, goal) joins the convolutions' output"""
    lidar_rays: int = 36
    """rays per LIDAR scan (``lidar_scans`` > 0)"""

    @classmethod
    def of(cls, agent) -> DDPGConfig:
        """A DDPG's config from the (typed) agent section: ``agent.ddpg`` and the LIDAR observation's shape."""
        keys = {f.name: getattr(agent.ddpg, f.name) for f in fields(DDPGSettings)}
        return cls(**keys, lidar_scans=agent.lidar_scans, lidar_rays=agent.lidar_rays)

    def problems(self):
        yield from super().problems()
        yield from lidar_problems(self)


def lidar_problems(section):
    """The LIDAR observation's shape (``lidar_scans``, ``lidar_rays`` of ``section``) must fit the convolutions."""
    if section.lidar_scans < 0:
        yield ConfigValueError("lidar_scans", section.lidar_scans, "it must be >= 0 (0: no LIDAR encoder)")
    if section.lidar_scans and section.lidar_rays < 8:
        yield ConfigValueError("lidar_rays", section.lidar_rays, "a scan needs at least 8 rays for the convolutions")


def td3_options(cfg: DDPGConfig) -> list[str]:
    """The TD3 options ``cfg`` turns on (``worldmodel.models.td3.TD3``): none for Lillicrap's DDPG."""
    on = {"twin_critics": cfg.twin_critics, "policy_delay": cfg.policy_delay > 1, "target_noise": cfg.target_noise > 0}
    return [f"agent.ddpg.{key}" for key, set_ in on.items() if set_]
