"""Phase 3: train one agent, whichever its learner: the paper's DDPG acting from [z_t, zhat_{t+1}] in the live
simulator, with reward R1 or R2, or another learner (``agent.learner``, worldmodel/registry.py), or a scenario
family's own (its ``system.train``).

    python -m worldmodel.train_agent experiment=NAME reward=r1|r2 scale=...
    python -m worldmodel.train_agent -m experiment=NAME reward=r1,r2        # both, through Hydra multirun

Writes ``runs/NAME/agent_<reward>[_<variant>][-<obs>]/seed<K>/``: ``last.pt``, ``best.pt``, TensorBoard and
``metrics.json`` when finished; ``resume=true`` continues a stopped run exactly. The paper's DDPG:
worldmodel/learners/ddpg.py.
"""

from __future__ import annotations

import logging

from . import artifacts, registry
from .common import StageError, seed_everything, set_threads
from .config import hydra_main, validate
from .training import TrainingRun

log = logging.getLogger(__name__)


def run(cfg) -> dict:
    typed = validate(cfg)
    set_threads(typed.threads)
    agent_id = artifacts.AgentId.of(cfg)
    family = registry.of_reward(agent_id.reward)
    if family.trains(typed.agent.learner, typed.agent.obs):  # e.g. Chae's or Merola's DQN, Kim's LIDAR agents
        return run_family(cfg, agent_id, family.name)
    learner = registry.learner(typed.agent.learner)
    if not learner.module:
        raise StageError(
            f"no trainer for agent.learner={learner.name} on family {family.name} (reward {agent_id.reward}): "
            f"the family's learners are {', '.join(family.learners) or 'none of its own'}"
        )
    return registry.learner_module(learner.name).run(cfg, agent_id)


def run_family(cfg, agent_id, family: str) -> dict:
    """A family's own learner (``worldmodel/families/<family>``; e.g. Chae et al.'s braking DQN, Kim et al.'s LIDAR
    agents). Its ``train`` returns the metrics, with ``summary`` (a line for the log)."""
    peer = registry.system(family)
    # the training seed, into the process-wide generators too, which a checkpoint saves and restores
    seed_everything(agent_id.seed)
    with TrainingRun.for_agent(cfg, agent_id) as run_:
        metrics = peer.train(cfg, run_, agent_id)
        if metrics.get("stopped"):
            return metrics
        log.info("[%s] %s; wrote %s", agent_id.policy, peer.summary(metrics), run_.dir)
        return run_.finish(metrics)


main = hydra_main("train_agent")(run)

if __name__ == "__main__":
    main()
