"""The privileged planner as the LIDAR agent's teacher: its demonstrations, the actor's cloning on them and the
DAgger rounds that relabel the student's own states."""

from __future__ import annotations

import logging

import numpy as np

from envs.kim import kim_action, kim_action_for
from envs.streams import KIM_DAGGER_SCENARIOS, KIM_DEMO_SCENARIOS

from ...common import StageError
from .observe import LidarObserver, training_scenario

log = logging.getLogger(__name__)
HELD_OUT_SHARE = 0.1  # the last tenth of the demonstration episodes (at least one) stops the cloning early
STEERING_LABEL = 0.15  # a label steers (agent.kim.bc_steer_weight) above this share of full steering; the planner: 0.3+


def teacher(cfg):
    """The planner that demonstrates to the LIDAR agent: ``evaluate.oracle`` planning from the first frame,
    steering to ``demos.teacher_sides``, minimising Kim's ISS cost at the family's 0.1 s steps."""
    from envs.planner import PrivilegedPlanner

    from ...config import teacher_settings

    return PrivilegedPlanner.from_settings(**{**teacher_settings(cfg), "step_s": 0.1, "reward": "kim_unaware"})


def planner_demonstrations(cfg, env, see: LidarObserver, hp, split: str):
    """``demos.episodes`` episodes of the planner on the training distribution, recorded as the LIDAR agent would
    live them: its observation, the planner's controls as the Kim action that asks for them (``kim_action_for``),
    the scaled rewards folded into ``agent.ddpg.n_step`` returns. Episode i depends only on (seed, i), so the
    demonstrations are the same in a resumed run. ``split``: ``train`` or ``validation`` (the last tenth).
    Returns (replay buffer of the transitions, planner's avoidance % over the split's episodes)."""
    from tqdm import tqdm

    from ...config import validate
    from ...models.ddpg import NStepWindow, ReplayBuffer

    typed = validate(cfg)
    planner = teacher(cfg)
    n = typed.demos.episodes
    if n < 2:
        raise StageError(f"demos.episodes={n}: cloning needs at least 2 episodes, one of them held out")
    first_held_out = n - max(1, round(HELD_OUT_SHARE * n))
    episodes = list(range(first_held_out, n) if split == "validation" else range(first_held_out))
    buffer = ReplayBuffer(max(1, len(episodes) * 60), see.dim, 2)  # 5 s of 0.1 s steps, and room to spare
    window, scale, avoided = NStepWindow(hp.ddpg.n_step, hp.ddpg.gamma), hp.reward_scale, 0
    for i in tqdm(episodes, desc=f"planner demonstrations ({split})", unit="episode"):
        env.reset(options={"scenario": training_scenario(typed, KIM_DEMO_SCENARIOS, i)})
        planner.reset()
        planner.bind(env)
        see.reset()
        x = see(env)
        while True:
            u = kim_action_for(planner.act(None, None), env.ego.v)
            _, reward, terminated, truncated, info = env.step(kim_action(u, env.ego.v))
            see.note_action(u)
            x_next = see(env)
            for tr in window.push(x, u, reward * scale, x_next, terminated):
                buffer.add(*tr)
            x = x_next
            if terminated or truncated:
                break
        for tr in window.flush():
            buffer.add(*tr)
        avoided += int(not env.collisions)
    return buffer, round(100.0 * avoided / max(1, len(episodes)), 1)


def dagger_labels(cfg, env, see: LidarObserver, agent, round_: int):
    """One DAgger round: the student drives ``agent.dagger_episodes`` training-distribution episodes, and at every
    step the planner, replanning from the true state, says what it would do there. Returns the student's inputs,
    the planner's answers as Kim actions, and the student's avoidance % over the round."""
    from tqdm import tqdm

    from ...config import validate

    typed = validate(cfg)
    planner = teacher(cfg)
    xs, ys, avoided, n = [], [], 0, typed.agent.dagger_episodes
    for e in tqdm(range(n), desc=f"DAgger round {round_}", unit="episode"):
        env.reset(options={"scenario": training_scenario(typed, KIM_DAGGER_SCENARIOS, round_, e)})
        planner.reset()
        planner.bind(env)
        see.reset()
        while True:
            x = see(env)
            planner.plan = None  # a fresh plan from the student's state, not the continuation of an earlier one
            xs.append(x)
            ys.append(kim_action_for(planner.act(None, None), env.ego.v))
            a = agent.act(x, explore=False)
            _, _, terminated, truncated, _ = env.step(kim_action(a, env.ego.v))
            see.note_action(a)
            if terminated or truncated:
                break
        avoided += int(not env.collisions)
    return np.asarray(xs, np.float32), np.asarray(ys, np.float32), round(100.0 * avoided / max(1, n), 1)


def learn_from_planner(cfg, env, see: LidarObserver, agent, hp, writer, cloned: bool) -> tuple:
    """The planner's demonstrations for DDPG from demonstrations (``agent.demo_share``, ``agent.ddpg.bc_weight``) and,
    unless ``cloned`` (a resumed run), the actor's cloning on them (``agent.bc_pretrain_steps``) with
    ``agent.dagger_rounds`` DAgger rounds. ``hp``: the typed agent section. Returns (demonstration buffer, what was
    measured on the way)."""
    from ...config import validate
    from ...imitation import cloning_fit
    from ...learners.cloning import clone

    demos, planner_avoided = planner_demonstrations(cfg, env, see, hp, "train")
    episodes = validate(cfg).demos.episodes
    info = {"episodes": episodes, "transitions": len(demos), "planner_avoidance": planner_avoided}
    log.info("%d demonstration transitions; the planner avoided %.1f %%", len(demos), planner_avoided)
    if cloned or hp.bc_pretrain_steps <= 0:
        return demos, info
    held_out, _ = planner_demonstrations(cfg, env, see, hp, "validation")
    inputs, targets = demos.obs[: len(demos)], demos.actions[: len(demos)]
    for round_ in range(hp.dagger_rounds + 1):
        if round_:
            x, y, student = dagger_labels(cfg, env, see, agent, round_)
            inputs, targets = np.concatenate([inputs, x]), np.concatenate([targets, y])
            info[f"dagger_round{round_}"] = {"labels": len(x), "student_avoidance": student}
            log.info("DAgger round %d: the student avoided %.1f %%, %d labels", round_, student, len(x))
        w = hp.kim.bc_steer_weight
        weights = None if w == 1.0 else np.where(np.abs(targets[:, 1]) > STEERING_LABEL, w, 1.0)  # None: as before
        clone(agent, inputs, targets, hp, writer, round_, held_out, weights)
        info[f"after_cloning_round{round_}"] = cloning_fit(agent, held_out)
    agent.sync_targets()
    return demos, info
