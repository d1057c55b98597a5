"""Learning from the privileged planner through the frozen world model (docs/design.md §5).

"Learning by cheating": the planner reads the true state; the student sees only what the camera gives, through the
world model. This module turns the planner's recorded demonstrations (``worldmodel.demonstrate``) into agent
transitions, measures how well an actor fits them, runs DAgger rounds in which the planner labels the student's own
states, and mixes demonstrations into DDPG's minibatches; the cloning itself is a fit of the training loop
(``learners/cloning.py``). ``train_agent`` uses it.
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from envs import sample_focus_scenario
from envs.planner import PrivilegedPlanner
from envs.streams import DAGGER_SCENARIOS

from . import loading
from .action_map import ActionMap
from .agent_obs import WorldModelView, encode_episode
from .common import make_env
from .config import teacher_settings, validate
from .models.ddpg import DDPG, NStepWindow, ReplayBuffer


def demonstration_buffer(
    cfg, encoder, action_map: ActionMap, reward: str, hp, split: str | None = None
) -> tuple[ReplayBuffer, dict]:
    """The planner's demonstrations (``worldmodel.demonstrate``) as agent transitions: every frame through the
    frozen world model as a live run would feed it, every action as the actor output that asks for it, rewards
    scaled and folded into ``agent.ddpg.n_step`` returns like the agent's own. ``hp``: ``cfg``'s agent section (typed,
    or as composed). ``split``: the store's ``train`` or ``validation`` episodes, or all of them."""
    store = loading.open_demos(cfg)
    splits = ("train", "validation") if split is None else (split,)
    episodes = sorted(i for s in splits for i in store.episodes(s))
    total = sum(int(store.attrs(i)["n_steps"]) for i in episodes)
    buffer = ReplayBuffer(max(1, total), encoder.dim, 2)
    window = NStepWindow(hp.ddpg.n_step, hp.ddpg.gamma)
    for i in tqdm(episodes, desc=f"encode demonstrations ({split or 'all'})", unit="episode"):
        seg, speed, action = store.read(i, "seg"), store.read(i, "speed"), store.read(i, "action")
        rewards = store.read(i, f"reward_{reward}") * hp.reward_scale
        terminated = bool(store.attrs(i)["terminated"])
        states = encode_episode(encoder, seg, speed, action)
        n = len(seg) - 1
        for t in range(n):
            u = action_map.from_env(action[t], float(speed[t]))
            for tr in window.push(states[t], u, float(rewards[t]), states[t + 1], terminated and t == n - 1):
                buffer.add(*tr)
        for tr in window.flush():
            buffer.add(*tr)
    store.close()
    return buffer, {"episodes": len(episodes), "transitions": len(buffer)}


def dagger_labels(cfg, agent: DDPG, encoder, action_map: ActionMap, round_: int):
    """One DAgger round (Ross et al. 2011): the student drives ``agent.dagger_episodes`` focus-mix episodes with the
    camera; at every step the planner, replanning from the true state, says what it would do there. Returns the
    student's inputs, the planner's actions as actor outputs, and how the student's episodes ended.

    Cloning the planner's own episodes teaches the student the planner's states only; there its recurrent state
    already carries the planner's first swerve, which the student, acting alone, never made (measured: on held-out
    demonstrations the cloned actor steers 0.14 at the first frame of a planner swerve and 0.69 by the third)."""
    typed = validate(cfg)
    sim = make_env(cfg)
    view = WorldModelView(sim, encoder, action_map)
    planner = PrivilegedPlanner.from_settings(**teacher_settings(cfg))
    f = typed.demos.focus
    xs, ys, hits = [], [], {"pedestrian": 0, "vehicle": 0, "static": 0}
    for e in tqdm(range(typed.agent.dagger_episodes), desc=f"DAgger round {round_}", unit="episode"):
        rng = np.random.default_rng([typed.seed, DAGGER_SCENARIOS, round_, e])
        spec = sample_focus_scenario(rng, f.hazard_share, tuple(f.speed_range), tuple(f.ttc_range))
        obs, _ = view.reset(options={"scenario": spec})
        planner.reset(spec.seed)
        planner.bind(sim)
        done = False
        while not done:
            planner.plan = None  # a fresh plan from this state, not the continuation of an earlier one
            label = planner.act(None, None)
            xs.append(obs)
            ys.append(action_map.from_env(label, view.speed))
            obs, _, terminated, truncated, info = view.step(agent.act(obs, explore=False))
            done = terminated or truncated
        for kind in hits:
            hits[kind] += int(info["outcome"][f"{kind}_collision"])
    sim.close()
    return np.asarray(xs, np.float32), np.asarray(ys, np.float32), hits


def cloning_fit(agent: DDPG, held_out: ReplayBuffer) -> dict:
    """How well the actor reproduces the planner on held-out demonstrations: mean |mu(s) - a|^2, beside the same
    for the best constant action (what an actor blind to its input can do) and for the zero action (braking,
    with ``agent.anchor=brake``)."""
    obs = torch.from_numpy(held_out.obs[: len(held_out)])
    target = torch.from_numpy(held_out.actions[: len(held_out)])
    with torch.no_grad():
        fit = ((agent.actor(obs.to(agent.device)).cpu() - target) ** 2).sum(-1).mean().item()
    constant = ((target.mean(0) - target) ** 2).sum(-1).mean().item()
    zero = (target**2).sum(-1).mean().item()
    return {"actor": round(fit, 5), "best_constant": round(constant, 5), "zero": round(zero, 5)}


def mixed_batch(buffer: ReplayBuffer, demos: ReplayBuffer | None, size: int, share: float, rng) -> dict:
    """A minibatch with ``round(share * size)`` demonstration samples, marked by ``batch["demo"]``."""
    n_demo = int(round(share * size)) if demos is not None else 0
    batch = buffer.sample(size - n_demo, rng)
    mask = torch.zeros(size - n_demo)
    if n_demo:
        extra = demos.sample(n_demo, rng)
        batch = {k: torch.cat([batch[k], extra[k]]) for k in batch}
        mask = torch.cat([mask, torch.ones(n_demo)])
    batch["demo"] = mask
    return batch
