"""The policies on family chae: the scripted braking rules, the trained dqn agents (one checkpoint or the greedy
mean-Q ensemble of several seeds) and how a checkpoint becomes a policy."""

from __future__ import annotations

import logging

import numpy as np

from envs.chae import (
    BRAKE_LEVELS,
    SAFETY_LINE_M,
    BrakeAtTrigger,
    ClosingSpeedBraking,
    LatestSafeBraking,
    brake_action,
)

from ... import artifacts, loading
from ...artifacts import AgentId
from ...common import StageError, decision_device
from ..common import DQNPolicy
from .observe import observer

log = logging.getLogger(__name__)


class QEnsemble:
    """Several trained DQNs acting as one: greedy on the mean of their Q-values (Chae's four brake levels)."""

    def __init__(self, members):
        self.members = list(members)

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        return np.mean([m.q_values(obs) for m in self.members], axis=0)

    def act(self, obs: np.ndarray, step: int | None = None, explore: bool = False) -> int:
        if explore:
            raise ValueError("a Q-ensemble only acts greedily: it is evaluated, not trained")
        return int(np.argmax(self.q_values(obs)))


def ensembles(agents: list[AgentId], policies: list[DQNPolicy], k: int) -> list[DQNPolicy]:
    """``evaluate.chae.ensemble``: per policy name (variant and observation), one ``QEnsemble`` of each ``k``
    consecutive seeds 0..k-1, k..2k-1, ..., named ``<policy>_ensemble<k>`` with the group's index as its seed. A
    group with a seed missing is left out (logged), so an ensemble is always the same runs."""
    by_name: dict[str, dict[int, DQNPolicy]] = {}
    for agent, policy in zip(agents, policies, strict=True):
        by_name.setdefault(agent.policy, {})[agent.seed] = policy
    out = []
    for name, seeds in by_name.items():
        for group in range(max(seeds) // k + 1):
            wanted = list(range(group * k, (group + 1) * k))
            missing = [s for s in wanted if s not in seeds]
            if missing:
                log.info("[eval chae] no %s_ensemble%d over seeds %s: seeds %s not trained", name, k, wanted, missing)
                continue
            members = [seeds[s] for s in wanted]
            see = members[0].see  # the members' observers are alike; one makes the ensemble's input
            out.append(DQNPolicy(f"{name}_ensemble{k}", QEnsemble(m.agent for m in members), see, group))
    return out


class TTCBraking:
    """Brake fully once the time to reach the safety line at the current speed falls below ``threshold_s``, while
    the pedestrian is crossing (privileged, as an AEB with a perfect sensor)."""

    name = "ttc_braking"

    def __init__(self, threshold_s: float = 1.0):
        self.threshold_s = float(threshold_s)

    def reset(self, seed=None) -> None:
        self.braking = False

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        env, state = self.env, self.env.family_state
        if not self.braking and state is not None and state.started:
            gap = state.ped_x - SAFETY_LINE_M - (env.ego.x + env.params.length / 2)
            self.braking = gap <= self.threshold_s * max(env.ego.v, 1e-6)
        return brake_action(0 if self.braking else 3)


class StraightBraking(BrakeAtTrigger):
    """Straight-line braking from the hazard's onset, as on the paper's bank: full braking from the step after
    the pedestrian starts to cross (the physics check's policy)."""

    name = "braking"


# closing_braking is the one not privileged: it reads the agent's own noisy state (envs.chae.ClosingSpeedBraking)
SCRIPTED = {
    "braking": StraightBraking,
    "ttc_braking": TTCBraking,
    "latest_safe_braking": LatestSafeBraking,
    "closing_braking": ClosingSpeedBraking,
}


def load_policy(cfg, agent_id: AgentId) -> DQNPolicy:
    """A trained dqn agent, built with the hyperparameters it was trained with: the checkpoint ``agent.chae.select``
    chose on its validation draw (``best.pt``) when the run validated, else the last one."""
    state = loading.load_agent_state(cfg, agent_id, "last")
    # last.pt says whether the run validated (a best.pt alone could be left from another run's settings); a chae
    # checkpoint is small, so reading best.pt after it costs little
    if state.get("curve", {}).get("validation"):
        state = loading.load_agent_state(cfg, agent_id, "best")
        log.info("[eval chae] %s: best.pt, episode %d, chosen on the validation draw", agent_id.key, state["episode"])
    return policy_from_state(cfg, agent_id, state)


def policy_from_state(cfg, agent_id: AgentId, state: dict) -> DQNPolicy:
    """The greedy policy of one dqn checkpoint of run ``agent_id`` (``last.pt``, ``best.pt`` or a kept one)."""
    from omegaconf import OmegaConf

    from ...config import agent_preset
    from ...models.dqn import DQN, DQNConfig

    if state.get("learner") != "dqn":
        raise StageError(
            f"{agent_id.dir(cfg)} is not a dqn agent; delete it or move it out of {artifacts.runs_root(cfg)}"
        )
    # checkpoints from before agent.chae.noise_m were all trained at the default 0.1 m
    see = observer(cfg, state["obs"], noise_m=state.get("noise_m", 0.1))
    if see.dim != state["obs_dim"]:
        raise StageError(
            f"{agent_id.dir(cfg)} was trained on inputs of size {state['obs_dim']}, the observation "
            f"{state['obs']} gives {see.dim} (the world model changed?); retrain it with "
            f"`python -m worldmodel.train_agent experiment={cfg.experiment} agent=dqn_chae seed={agent_id.seed}`"
        )
    if "dqn_config" in state:
        hp = DQNConfig(**state["dqn_config"])
    else:  # an early checkpoint: the preset it was trained with
        hp = OmegaConf.to_object(
            OmegaConf.merge(OmegaConf.structured(DQNConfig), agent_preset(cfg, agent_id.variant).dqn)
        )
    agent = DQN(see.dim, len(BRAKE_LEVELS), hp, agent_id.seed, device=decision_device(cfg))
    agent.load_state_dict(state["agent"])
    return DQNPolicy(agent_id.policy, agent, see, agent_id.seed)
