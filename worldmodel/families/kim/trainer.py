"""Training Kim et al.'s LIDAR agent (``train``, ``summary``) and the trained agent as a policy (``load_policy``)."""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np

from envs.kim import kim_action
from envs.streams import KIM_TRAINING_EPISODES

from ... import artifacts, loading
from ...artifacts import AgentId
from ...common import StageError, decision_device, percent, resolve_device
from ...learners.loop import Callbacks, TrainingLoop
from ..common import TrueStateView
from .observe import GOAL_REWARDS, LidarObserver, family_env, observer, training_scenario
from .teach import learn_from_planner

ROLLING = 100
CHECKPOINT_EPISODES = 200


def train(cfg, run_, agent_id: AgentId) -> dict:
    """``train_agent`` with ``agent.obs=lidar``: DDPG on family kim for ``agent.kim.total_steps`` steps, or the
    LIDAR chooser (``agent.learner=kim_chooser``, ``chooser.train``), or the counterfactual-cost DDPG
    (``agent.learner=counterfactual``, ``counterfactual.train``)."""
    from ...config import validate

    if agent_id.family != "kim":
        raise StageError(
            f"the LIDAR agent learns on family kim: use reward=kim_unaware or kim_aware, not {agent_id.reward}"
        )
    typed = validate(cfg)
    if typed.agent.learner == "kim_chooser":
        from . import chooser

        return chooser.train(cfg, run_, agent_id)
    if typed.agent.learner == "counterfactual":
        from . import counterfactual

        return counterfactual.train(cfg, run_, agent_id)
    if not typed.agent.lidar_scans and typed.agent.obs == "lidar":
        raise StageError("obs=lidar needs the LIDAR front end: agent.lidar_scans=4 (agent=ddpg_kim sets it)")
    return LidarRun(cfg, typed, run_, agent_id).train()


class LidarEpisodes:
    """Family kim's training episodes through the LIDAR view: the DDPG's action in [-1, 1]^2 becomes the family's
    steering and acceleration (``kim_action``)."""

    def __init__(self, env, see: LidarObserver, typed):
        self.env, self.see, self.typed = env, see, typed

    def start(self, episode: int):
        self.env.reset(options={"scenario": training_scenario(self.typed, KIM_TRAINING_EPISODES, episode)})
        self.see.reset()
        return self.see(self.env)

    def step(self, action) -> tuple:
        _, reward, terminated, truncated, info = self.env.step(kim_action(action, self.env.ego.v))
        self.see.note_action(action)
        return self.see(self.env), reward, terminated, truncated, info


class LidarRun(Callbacks):
    """One LIDAR DDPG run on family kim: its learner, view and env, resumed from ``run_``'s checkpoint, and
    the planner's demonstrations where the preset learns from them."""

    def __init__(self, cfg, typed, run_, agent_id: AgentId):
        """``typed``: ``cfg`` validated."""
        from ...learners.ddpg import DDPGLearner
        from ...models.ddpg import DDPGConfig
        from ...models.td3 import make_agent

        self.typed, self.run_, self.agent_id = typed, run_, agent_id
        self.hp = hp = typed.agent  # the typed agent section: DDPG's keys (hp.ddpg) and the training loop's
        self.see = see = observer(typed, agent_id.reward)
        self.env = family_env(cfg, agent_id.reward)
        ddpg = DDPGConfig.of(hp)
        if hp.obs != "lidar":  # the true state: the same layers without the LIDAR's convolutions
            ddpg = dataclasses.replace(ddpg, lidar_scans=0)
        agent = make_agent(see.dim, 2, ddpg, seed=typed.seed, device=resolve_device(typed.device))
        self.learner = DDPGLearner(agent, hp.reward_scale, hp.demo_share)
        episode, self.curve = 0, {"return": [], "crash": [], "end": []}
        if run_.state is not None:
            episode = self.resume(run_.state)
        self.demo_info = {}
        if hp.demo_share > 0 or (hp.bc_pretrain_steps > 0 and run_.state is None):  # resumed: cloned already
            self.learner.demos, self.demo_info = learn_from_planner(
                cfg, self.env, see, self.learner.agent, hp, run_.side_writer("pretrain"), cloned=run_.state is not None
            )
        if run_.state is not None:  # the cloning's figures, which only the run that cloned measured
            self.demo_info = {**self.demo_info, **run_.state.get("demonstrations", {})}
        self.recent: deque = deque((not c for c in self.curve["crash"][-ROLLING:]), maxlen=ROLLING)
        self.loop = TrainingLoop(self.learner, LidarEpisodes(self.env, see, typed), run_, self, episode=episode)

    def resume(self, state: dict) -> int:
        """Restore the learner and the curve; returns the checkpoint's episode count."""
        if state["obs_dim"] != self.see.dim:
            raise StageError(
                f"{self.run_.last} expects inputs of size {state['obs_dim']}, the LIDAR view gives {self.see.dim}; "
                f"delete {self.run_.dir} to retrain"
            )
        self.learner.load_state_dict(state)
        self.curve = state["curve"]
        self.run_.resumed(f"step {self.learner.steps}, episode {state['episode']}")
        return int(state["episode"])

    def snapshot(self) -> None:
        hp = self.hp
        self.run_.save(
            {
                **self.learner.state_dict(),
                "episode": self.loop.episode,
                "curve": self.curve,
                "obs": self.hp.obs,
                "obs_dim": self.see.dim,
                "lidar_speed": self.see.speed,
                "learner": "ddpg",
                "actor_hidden": list(hp.ddpg.actor_hidden),
                "ddpg_config": dataclasses.asdict(self.learner.agent.cfg),
                "reward": self.agent_id.reward,
                "demonstrations": self.demo_info,
            }
        )

    def on_episode(self, loop, o: dict, ret: float, length: int) -> None:
        crashed = bool(o["vehicle_collision"] or o["static_collision"] or o["pedestrian_collision"])
        self.curve["return"].append(float(ret))
        self.curve["crash"].append(crashed)
        self.curve["end"].append(o["end"])
        self.recent.append(not crashed)
        writer, step = self.run_.writer, loop.step
        writer.add_scalar("episode/return", ret, step)
        writer.add_scalar("episode/avoidance_rolling", float(np.mean(self.recent)), step)
        for k, v in loop.losses.items():
            writer.add_scalar(f"train/{k}", v, step)
        if loop.episode % CHECKPOINT_EPISODES == 0:
            self.snapshot()

    def train(self) -> dict:
        from tqdm import tqdm

        run_, loop, total = self.run_, self.loop, self.hp.kim.total_steps
        run_.restore_random_state()  # building the networks and views drew from them
        with tqdm(total=total, initial=loop.step, desc=f"ddpg kim ({self.agent_id.reward})", unit="step") as bar:
            loop.run(lambda: loop.step >= total, bar)
        self.snapshot()
        self.env.close()
        if run_.stop.requested:
            return run_.stopped(loop.step)
        last = self.curve["crash"][-ROLLING:]
        return {
            "reward": self.agent_id.reward,
            "obs": self.hp.obs,
            "steps": loop.step,
            "episodes": loop.episode,
            "recent_avoidance": float(1.0 - np.mean(last)) if last else None,
            "curve": self.curve,
            "demonstrations": self.demo_info,
        }


def summary(metrics: dict) -> str:
    """One log line for a finished training run."""
    if metrics.get("learner") == "kim_chooser":
        from .chooser import summary as chooser_summary

        return chooser_summary(metrics)
    if metrics.get("learner") == "counterfactual":
        last = metrics["history"][max(k for k in metrics["history"] if k.startswith("actor"))]
        return (
            f"{metrics.get('labelled_states', 0)} labelled decision states; held out, the actor's predicted cost "
            f"{last['predicted_cost']:.2f} against braking's {last['predicted_braking_cost']:.2f}"
        )
    steps, episodes, avoided = metrics["steps"], metrics["episodes"], metrics["recent_avoidance"]
    return f"{steps} steps, {episodes} episodes; avoidance in the last 100: {percent(avoided)}"


# ----------------------------------------------------------------------------- policies
class LidarPolicy:
    """A trained LIDAR DDPG actor, without exploration, behind the scripted-policy interface."""

    def __init__(self, name: str, agent, see: LidarObserver, policy_seed: int):
        self.name, self.agent, self.see, self.policy_seed = name, agent, see, policy_seed

    def reset(self, seed=None) -> None:
        self.see.reset(seed)

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        a = self.agent.act(self.see(self.env), explore=False)
        self.see.note_action(a)
        return kim_action(a, self.env.ego.v)


def load_policy(cfg, agent_id: AgentId) -> tuple:
    """(policy, sees the camera) for a trained kim agent: a LIDAR DDPG (agent=ddpg_kim; with obs=privileged, on the
    true state), the LIDAR chooser (agent=kim_chooser), the counterfactual-cost DDPG (agent=counterfactual_kim), or
    a world-model agent (agent=ddpg_wm_kim) that acts from camera frames at the world model's step length."""
    from ...models.ddpg import DDPGConfig
    from ...models.td3 import make_agent
    from ...policies import learned_policy

    state = loading.load_agent_state(cfg, agent_id, "last")
    if state.get("learner") == "kim_chooser":
        from .chooser import policy

        return policy(state, agent_id.policy), False
    if state.get("learner") == "counterfactual":
        from .counterfactual import policy as shift_policy

        return shift_policy(state, agent_id.policy), False
    if state.get("obs", "worldmodel") == "worldmodel":
        return learned_policy(cfg, agent_id, state)[0], True
    if state.get("obs") not in ("lidar", "privileged"):
        raise StageError(
            f"{agent_id.dir(cfg)} is neither a LIDAR nor a world-model agent; delete it or move it out of "
            f"{artifacts.runs_root(cfg)}"
        )
    trained = state["ddpg_config"]  # the scans it was trained on
    if state["obs"] == "privileged":
        see = TrueStateView()
    else:
        see = LidarObserver(
            agent_id.reward in GOAL_REWARDS,
            int(trained["lidar_scans"]),
            int(trained["lidar_rays"]),
            bool(state.get("lidar_speed", False)),  # checkpoints before the option saw no speed
        )
    if see.dim != state["obs_dim"]:
        raise StageError(
            f"{agent_id.dir(cfg)} was trained on inputs of size {state['obs_dim']}, the LIDAR view gives "
            f"{see.dim}; retrain it with `python -m worldmodel.train_agent experiment={cfg.experiment} "
            f"agent=ddpg_kim reward={agent_id.reward} seed={agent_id.seed}`"
        )
    hp = DDPGConfig(**state["ddpg_config"])  # as it was trained, whatever the evaluation's agent section says
    agent = make_agent(see.dim, 2, hp, agent_id.seed, device=decision_device(cfg))
    agent.load_state_dict(state["agent"])
    return LidarPolicy(agent_id.policy, agent, see, agent_id.seed), False
