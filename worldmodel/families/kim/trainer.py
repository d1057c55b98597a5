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
from .observe import GOAL_REWARDS, LidarObserver, family_env, observer, training_scenario
from .teach import learn_from_planner

ROLLING = 100
CHECKPOINT_EPISODES = 200


def train(cfg, run_, agent_id: AgentId) -> dict:
    """``train_agent`` with ``agent.obs=lidar``: DDPG on family kim for ``agent.kim.total_steps`` steps, or the
    LIDAR chooser (``agent.learner=kim_chooser``, ``chooser.train``)."""
    from tqdm import tqdm

    from ...config import validate
    from ...imitation import mixed_batch
    from ...models.ddpg import DDPG, DDPGConfig, NStepWindow, ReplayBuffer

    if agent_id.family != "kim":
        raise StageError(
            f"the LIDAR agent learns on family kim: use reward=kim_unaware or kim_aware, not {agent_id.reward}"
        )
    typed = validate(cfg)
    if typed.agent.learner == "kim_chooser":
        from . import chooser

        return chooser.train(cfg, run_, agent_id)
    hp = typed.agent  # the typed AgentConfig: a DDPGConfig with the training loop's keys (ddpg_config)
    if not hp.lidar_scans:
        raise StageError("obs=lidar needs the LIDAR front end: agent.lidar_scans=4 (agent=ddpg_kim sets it)")
    total = hp.kim.total_steps
    see = observer(typed, agent_id.reward)
    env = family_env(cfg, agent_id.reward)
    agent = DDPG(see.dim, 2, hp, seed=typed.seed, device=resolve_device(typed.device))
    buffer = ReplayBuffer(hp.buffer_size, see.dim, 2)
    step, episode, curve = 0, 0, {"return": [], "crash": [], "end": []}
    if run_.state is not None:
        state = run_.state
        if state["obs_dim"] != see.dim:
            raise StageError(
                f"{run_.last} expects inputs of size {state['obs_dim']}, the LIDAR view gives {see.dim}; "
                f"delete {run_.dir} to retrain"
            )
        agent.load_state_dict(state["agent"])
        buffer.load_state_dict(state["buffer"])
        step, episode, curve = int(state["step"]), int(state["episode"]), state["curve"]
        run_.resumed(f"step {step}, episode {episode}")
    demos, demo_info = None, {}
    if hp.demo_share > 0 or (hp.bc_pretrain_steps > 0 and run_.state is None):  # resumed: cloned already
        demos, demo_info = learn_from_planner(
            cfg, env, see, agent, hp, run_.side_writer("pretrain"), cloned=run_.state is not None
        )
    if run_.state is not None:  # the cloning's figures, which only the run that cloned measured
        demo_info = {**demo_info, **run_.state.get("demonstrations", {})}

    def snapshot():
        run_.save(
            {
                "agent": agent.state_dict(),
                "buffer": buffer.state_dict(),
                "step": step,
                "episode": episode,
                "curve": curve,
                "obs": "lidar",
                "obs_dim": see.dim,
                "lidar_speed": see.speed,
                "learner": "ddpg",
                "actor_hidden": list(hp.actor_hidden),
                "ddpg_config": {f.name: getattr(hp, f.name) for f in dataclasses.fields(DDPGConfig)},
                "reward": agent_id.reward,
                "demonstrations": demo_info,
            }
        )

    window = NStepWindow(hp.n_step, hp.gamma)
    writer = run_.writer
    recent: deque = deque((not c for c in curve["crash"][-ROLLING:]), maxlen=ROLLING)
    scale = hp.reward_scale
    losses: dict = {}
    run_.restore_random_state()  # building the networks and views drew from them
    with tqdm(total=total, initial=step, desc=f"ddpg kim ({agent_id.reward})", unit="step") as bar:
        while step < total and not run_.stop.requested:
            env.reset(options={"scenario": training_scenario(typed, KIM_TRAINING_EPISODES, episode)})
            see.reset()
            x, ret = see(env), 0.0
            while True:
                a = agent.random_action() if step < hp.warmup_steps else agent.act(x, explore=True)
                _, reward, terminated, truncated, info = env.step(kim_action(a, env.ego.v))
                see.note_action(a)
                x_next = see(env)
                for transition in window.push(x, a, reward * scale, x_next, terminated):
                    buffer.add(*transition)
                if truncated and not terminated:
                    for transition in window.flush():
                        buffer.add(*transition)
                x, ret = x_next, ret + reward
                step += 1
                bar.update(1)
                if step > hp.warmup_steps and len(buffer) >= hp.batch_size:
                    if demos is None:  # the paper's agent, drawing exactly what it drew before demonstrations existed
                        batch = buffer.sample(hp.batch_size, agent.rng)
                    else:
                        batch = mixed_batch(buffer, demos, hp.batch_size, hp.demo_share, agent.rng)
                    losses = agent.update(batch)
                if terminated or truncated:
                    break
            o = info["outcome"]
            crashed = bool(o["vehicle_collision"] or o["static_collision"] or o["pedestrian_collision"])
            curve["return"].append(float(ret))
            curve["crash"].append(crashed)
            curve["end"].append(o["end"])
            recent.append(not crashed)
            episode += 1
            writer.add_scalar("episode/return", ret, step)
            writer.add_scalar("episode/avoidance_rolling", float(np.mean(recent)), step)
            for k, v in losses.items():
                writer.add_scalar(f"train/{k}", v, step)
            if episode % CHECKPOINT_EPISODES == 0:
                snapshot()
    snapshot()
    env.close()
    if run_.stop.requested:
        return run_.stopped(step)
    last = curve["crash"][-ROLLING:]
    return {
        "reward": agent_id.reward,
        "obs": "lidar",
        "steps": step,
        "episodes": episode,
        "recent_avoidance": float(1.0 - np.mean(last)) if last else None,
        "curve": curve,
        "demonstrations": demo_info,
    }


def summary(metrics: dict) -> str:
    """One log line for a finished training run."""
    if metrics.get("learner") == "kim_chooser":
        from .chooser import summary as chooser_summary

        return chooser_summary(metrics)
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
    """(policy, sees the camera) for a trained kim agent: a LIDAR DDPG (agent=ddpg_kim), the LIDAR chooser
    (agent=kim_chooser), or a world-model agent (agent=ddpg_wm_kim) that acts from camera frames at the world
    model's step length."""
    from ...models.ddpg import DDPG, DDPGConfig
    from ...policies import learned_policy

    state = loading.load_agent_state(cfg, agent_id, "last")
    if state.get("learner") == "kim_chooser":
        from .chooser import policy

        return policy(state, agent_id.policy), False
    if state.get("obs", "worldmodel") == "worldmodel":
        return learned_policy(cfg, agent_id, state)[0], True
    if state.get("obs") != "lidar":
        raise StageError(
            f"{agent_id.dir(cfg)} is neither a LIDAR nor a world-model agent; delete it or move it out of "
            f"{artifacts.runs_root(cfg)}"
        )
    trained = state["ddpg_config"]  # the scans it was trained on
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
    agent = DDPG(see.dim, 2, hp, agent_id.seed, device=decision_device(cfg))
    agent.load_state_dict(state["agent"])
    return LidarPolicy(agent_id.policy, agent, see, agent_id.seed), False
