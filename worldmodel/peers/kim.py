"""Kim et al. 2020 on our simulator: DDPG with a LIDAR front end against red-light runners, on family ``kim``.

    python -m worldmodel.train_agent experiment=NAME agent=ddpg_kim [reward=kim_aware] [seed=K]
    python -m worldmodel.train_agent experiment=NAME agent=ddpg_wm_kim [seed=K]     # the camera agent
    python -m worldmodel.evaluate experiment=NAME evaluate.family=kim

Training (``train_agent`` with ``agent.obs=lidar``): ``agent.peer_total_steps`` steps of family ``kim``
(envs/kim.py: the three scenarios, lanes and neutral cars drawn uniformly, the ego at U(10, 50) km/h), 0.1 s steps;
the existing DDPG (worldmodel/models/ddpg.py) with Kim's 1-D convolutions over the LIDAR's angle
(``agent.lidar_scans``). The observation is the last 4 scans of the 36-ray LIDAR and the previous action
(envs/lidar.py); with the goal-aware reward ``kim_aware`` (Eq. 10) also the distance and angle to the goal, as in the
paper. The action is (desired speed, steering angle), mapped onto our controls by ``envs.kim.kim_action``. Runs:
``runs/NAME/agent_kim_unaware_ddpg_kim/seedK/`` (and ``agent_kim_aware_ddpg_kim``), resumable, with TensorBoard
(return, rolling avoidance) and ``metrics.json`` with the learning curve.

Evaluation (``evaluate.family=kim``): Table 2's layout, avoidance % (no collision of any kind in the episode) and
mean injury (minus the summed Sobhani ISS, as the paper's table gives it) per scenario and overall, for every
LIDAR agent, every world-model agent trained on the family (``agent=ddpg_wm_kim``: camera frames, at the world
model's 1/15 s steps), the paper's street-trained agents as they are (``evaluate.kim.world_model_agents``), AEB-3m,
straight-line braking and the privileged planner, on ``evaluate.kim.trials`` seeded trials per
scenario (the first ``paper_trials`` of them make the paper-sized table), with 95 % Wilson intervals and pairwise
paired permutation tests on per-trial injury. Writes ``runs/NAME/eval_kim/``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import deque

import numpy as np

from envs.kim import CAR_LENGTH, SCENARIOS, Aeb3m, KimSpec, kim_action, kim_action_for
from envs.kim import sample as sample_kim
from envs.lidar import RANGE_M, LidarHistory
from envs.policies import StraightLineBraking
from envs.rewards import crash_iss
from envs.streams import KIM_BANK_CROSSING, KIM_DAGGER_SCENARIOS, KIM_DEMO_SCENARIOS, KIM_TRAINING_EPISODES

from .. import artifacts
from ..artifacts import AgentId
from ..common import StageError, make_env
from ..stats import paired_permutation_p, wilson
from .common import drawn, record_if_test, seal, world_model_step_s, write_rows

log = logging.getLogger(__name__)
FAMILY, PRESET, NCAP_REWARD = "kim", "ddpg_kim", "kim_unaware"  # the Peer interface (worldmodel/peers/__init__.py)
ROLLING = 100
CHECKPOINT_EPISODES = 200
GOAL_REWARDS = ("kim_aware",)  # rewards whose agent also sees the goal (Kim et al. §II-F)
# Table 2 (avoidance %, mean injury) per scenario 1 / 2 / 3 / all, as published
PAPER_TABLE_2 = {
    "goal-aware DDPG (paper)": ((82.00, 92.50, 97.00, 92.17), (-1.89, -0.54, -0.43, -0.94)),
    "goal-unaware DDPG (paper)": ((87.00, 89.00, 92.50, 87.83), (-2.66, -0.88, -1.11, -1.52)),
    "human drivers (paper)": ((16.67, 16.67, 0.00, 11.11), (-13.20, -14.21, -13.97, -13.79)),
    "AEB (paper)": ((31.50, 5.30, 0.00, 5.30), (-17.99, -19.22, -21.90, -19.67)),
}


# ----------------------------------------------------------------------------- what the agent sees
class LidarObserver:
    """Kim's observation: ``scans`` LIDAR scans of ``rays`` rays (the paper: 4 of 36) and the previous action
    (``envs.lidar.LidarHistory``), plus, for the goal-aware agent, the distance to the goal (/ 50 m) and its
    bearing from the heading (/ pi). The agent's ``lidar_scans`` and ``lidar_rays`` set both, so the encoder reads
    the scans it is given. ``speed`` (``agent.use_speed``; not the paper's) also appends the ego's speed / 20 m/s,
    which the scans only show as the change between them."""

    camera = False

    def __init__(self, goal: bool, scans: int = 4, rays: int = 36, speed: bool = False):
        self.history, self.goal, self.speed = LidarHistory(scans=scans, n_rays=rays), bool(goal), bool(speed)
        self.dim = self.history.dim + (2 if self.goal else 0) + (1 if self.speed else 0)

    def reset(self, seed=None) -> None:
        self.history.reset(seed)

    def note_action(self, action) -> None:
        self.history.note_action(action)

    def __call__(self, env, obs=None) -> np.ndarray:
        parts, ego = [self.history(env)], env.ego
        if self.goal:
            gx, gy = env.family_state.goal
            bearing = math.atan2(gy - ego.y, gx - ego.x) - ego.psi
            bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
            d = min(1.0, math.hypot(gx - ego.x, gy - ego.y) / RANGE_M)
            parts.append(np.array([d, bearing / math.pi], np.float32))
        if self.speed:
            parts.append(np.array([ego.v / 20.0], np.float32))
        return np.concatenate(parts)


def observer(cfg, reward: str):
    if str(cfg.agent.obs) != "lidar":
        raise StageError(
            f"Kim et al.'s agent (agent=ddpg_kim) sees the LIDAR (obs=lidar), not obs={cfg.agent.obs}; the camera "
            "agent on this family is agent=ddpg_wm_kim"
        )
    a = cfg.agent
    return LidarObserver(reward in GOAL_REWARDS, int(a.lidar_scans), int(a.lidar_rays), bool(a.use_speed))


def family_env(cfg, reward: str, camera: bool = False, step_s: float = 0.1):
    return make_env(cfg, camera=camera, family="kim", reward=reward, step_s=step_s)


def training_scenario(cfg, *stream: int) -> KimSpec:
    """A scenario of the training distribution (``agent.kim_impact_offset_spread`` says where the runner may
    strike), a function of (seed, ``stream``) only, so a resumed run draws what an uninterrupted one would;
    ``stream`` starts with a tag of envs/streams.py (``KIM_TRAINING_EPISODES`` and the others) and its indices."""
    rng = np.random.default_rng([int(cfg.seed), *map(int, stream)])
    return sample_kim(rng, float(cfg.agent.kim_impact_offset_spread))


def ddpg_config(cfg):
    """The agent section as the typed ``AgentConfig`` (a ``DDPGConfig`` with the training loop's keys)."""
    from ..config import validate

    return validate(cfg).agent


# ----------------------------------------------------------------------------- learning from the planner
HELD_OUT_SHARE = 0.1  # the last tenth of the demonstration episodes (at least one) stops the cloning early
STEERING_LABEL = 0.15  # a label steers (agent.bc_steer_weight) above this share of full steering; the planner: 0.3+


def teacher(cfg):
    """The planner that demonstrates to the LIDAR agent: ``evaluate.oracle`` planning from the first frame,
    steering to ``demos.teacher_sides``, minimising Kim's ISS cost at the family's 0.1 s steps."""
    from envs.planner import PrivilegedPlanner

    from ..config import teacher_settings

    return PrivilegedPlanner.from_settings(**{**teacher_settings(cfg), "step_s": 0.1, "reward": "kim_unaware"})


def planner_demonstrations(cfg, env, see: LidarObserver, hp, split: str):
    """``demos.episodes`` episodes of the planner on the training distribution, recorded as the LIDAR agent would
    live them: its observation, the planner's controls as the Kim action that asks for them (``kim_action_for``),
    the scaled rewards folded into ``agent.n_step`` returns. Episode i depends only on (seed, i), so the
    demonstrations are the same in a resumed run. ``split``: ``train`` or ``validation`` (the last tenth).
    Returns (replay buffer of the transitions, planner's avoidance % over the split's episodes)."""
    from tqdm import tqdm

    from ..models.ddpg import NStepWindow, ReplayBuffer

    planner = teacher(cfg)
    n = int(cfg.demos.episodes)
    if n < 2:
        raise StageError(f"demos.episodes={n}: cloning needs at least 2 episodes, one of them held out")
    first_held_out = n - max(1, round(HELD_OUT_SHARE * n))
    episodes = list(range(first_held_out, n) if split == "validation" else range(first_held_out))
    buffer = ReplayBuffer(max(1, len(episodes) * 60), see.dim, 2)  # 5 s of 0.1 s steps, and room to spare
    window, scale, avoided = NStepWindow(hp.n_step, hp.gamma), float(hp.reward_scale), 0
    for i in tqdm(episodes, desc=f"planner demonstrations ({split})", unit="episode"):
        env.reset(options={"scenario": training_scenario(cfg, KIM_DEMO_SCENARIOS, i)})
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

    planner = teacher(cfg)
    xs, ys, avoided, n = [], [], 0, int(cfg.agent.dagger_episodes)
    for e in tqdm(range(n), desc=f"DAgger round {round_}", unit="episode"):
        env.reset(options={"scenario": training_scenario(cfg, KIM_DAGGER_SCENARIOS, round_, e)})
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
    """The planner's demonstrations for DDPG from demonstrations (``agent.demo_share``, ``agent.bc_weight``) and,
    unless ``cloned`` (a resumed run), the actor's cloning on them (``agent.bc_pretrain_steps``) with
    ``agent.dagger_rounds`` DAgger rounds. Returns (demonstration buffer, what was measured on the way)."""
    from ..imitation import clone, cloning_fit

    demos, planner_avoided = planner_demonstrations(cfg, env, see, hp, "train")
    info = {"episodes": int(cfg.demos.episodes), "transitions": len(demos), "planner_avoidance": planner_avoided}
    log.info("%d demonstration transitions; the planner avoided %.1f %%", len(demos), planner_avoided)
    if cloned or hp.bc_pretrain_steps <= 0:
        return demos, info
    held_out, _ = planner_demonstrations(cfg, env, see, hp, "validation")
    inputs, targets = demos.obs[: len(demos)], demos.actions[: len(demos)]
    for round_ in range(int(hp.dagger_rounds) + 1):
        if round_:
            x, y, student = dagger_labels(cfg, env, see, agent, round_)
            inputs, targets = np.concatenate([inputs, x]), np.concatenate([targets, y])
            info[f"dagger_round{round_}"] = {"labels": len(x), "student_avoidance": student}
            log.info("DAgger round %d: the student avoided %.1f %%, %d labels", round_, student, len(x))
        w = float(cfg.agent.bc_steer_weight)
        weights = None if w == 1.0 else np.where(np.abs(targets[:, 1]) > STEERING_LABEL, w, 1.0)  # None: as before
        clone(agent, inputs, targets, hp, writer, round_, held_out, weights)
        info[f"after_cloning_round{round_}"] = cloning_fit(agent, held_out)
    agent.sync_targets()
    return demos, info


# ----------------------------------------------------------------------------- training
def train(cfg, run_, agent_id: AgentId) -> dict:
    """``train_agent`` with ``agent.obs=lidar``: DDPG on family kim for ``agent.peer_total_steps`` steps."""
    from tqdm import tqdm

    from ..imitation import mixed_batch
    from ..models.ddpg import DDPG, DDPGConfig, NStepWindow, ReplayBuffer

    if agent_id.family != "kim":
        raise StageError(
            f"the LIDAR agent learns on family kim: use reward=kim_unaware or kim_aware, not {agent_id.reward}"
        )
    hp = ddpg_config(cfg)
    if not hp.lidar_scans:
        raise StageError("obs=lidar needs the LIDAR front end: agent.lidar_scans=4 (agent=ddpg_kim sets it)")
    total = int(cfg.agent.peer_total_steps)
    see = observer(cfg, agent_id.reward)
    env = family_env(cfg, agent_id.reward)
    agent = DDPG(see.dim, 2, hp, seed=int(cfg.seed))
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
    scale = float(hp.reward_scale)
    losses: dict = {}
    run_.restore_random_state()  # building the networks and views drew from them
    with tqdm(total=total, initial=step, desc=f"ddpg kim ({agent_id.reward})", unit="step") as bar:
        while step < total and not run_.stop.requested:
            env.reset(options={"scenario": training_scenario(cfg, KIM_TRAINING_EPISODES, episode)})
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
    steps, episodes, avoided = metrics["steps"], metrics["episodes"], metrics["recent_avoidance"]
    return f"{steps} steps, {episodes} episodes; avoidance in the last 100: {avoided}"


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
    """(policy, sees the camera) for a trained kim agent: a LIDAR DDPG (agent=ddpg_kim), or a world-model agent
    (agent=ddpg_wm_kim) that acts from camera frames at the world model's step length."""
    from ..models.ddpg import DDPG, DDPGConfig
    from ..policies import learned_policy

    state = artifacts.load_agent_state(cfg, agent_id, "last")
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
    agent = DDPG(see.dim, 2, hp, agent_id.seed)
    agent.load_state_dict(state["agent"])
    return LidarPolicy(agent_id.policy, agent, see, agent_id.seed), False


def scripted(cfg) -> list:
    """``evaluate.kim.policies``, in their order: braking, AEB-3m and the planner (minimising the ISS cost)."""
    from envs.planner import PrivilegedPlanner

    from ..config import oracle_settings

    def oracle():
        settings = {**oracle_settings(cfg), "step_s": 0.1, "reward": "kim_unaware"}
        return PrivilegedPlanner.from_settings(**settings)

    make = {"braking": StraightLineBraking, "aeb3m": Aeb3m, "oracle": oracle}
    return [make[name]() for name in cfg.evaluate.kim.policies]


# ----------------------------------------------------------------------------- evaluation
def bank(c) -> list[KimSpec]:
    """``c.trials`` seeded trials per scenario; scenario k's first ``c.paper_trials`` make the paper-sized table. Every
    trial's runner crosses the ego at ``c.impact_offset`` (0 by default, as in training), or uniformly within
    ``c.impact_offset_spread`` of it."""
    out, half = [], CAR_LENGTH / 2
    for k, scenario in enumerate(SCENARIOS):
        rng = np.random.default_rng([int(c.seed), k])
        crossing = np.random.default_rng([int(c.seed), k, KIM_BANK_CROSSING])  # the other fields stay the same
        for _ in range(int(c.trials)):
            spec = sample_kim(rng)
            offset = float(c.impact_offset)
            if c.impact_offset_spread > 0:
                low, high = max(-half, offset - c.impact_offset_spread), min(half, offset + c.impact_offset_spread)
                offset = float(crossing.uniform(low, high))
            out.append(KimSpec(**{**spec.to_dict(), "scenario": scenario, "impact_offset": offset}))
    return out


COLUMNS = [
    "policy",
    "policy_seed",
    "trial",
    "scenario",
    "ego_speed",
    "neutral",
    "end",
    "avoided",
    "crashes",
    "first_crash",
    "iss_kmh",
    "iss_ms",
    "hit_runner",
    "rear_ended",
]


def run_policy(env, policy, specs, policy_seed: int = 0) -> list[dict]:
    from tqdm import tqdm

    from envs.rollout import rollout

    rows = []
    per = {s: 0 for s in SCENARIOS}
    for spec in tqdm(specs, desc=policy.name, unit="trial"):
        o = rollout(env, policy, spec).outcome
        hits = list(env.collisions)
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": policy_seed,
                "trial": per[spec.scenario],
                "scenario": spec.scenario,
                "ego_speed": spec.ego_speed,
                "neutral": int(spec.neutral),
                "end": o["end"],
                "avoided": int(not hits),
                "crashes": len(hits),
                "first_crash": hits[0]["class"] if hits else "",
                "iss_kmh": crash_iss(hits, "kmh"),
                "iss_ms": crash_iss(hits, "ms"),
                "hit_runner": int(any(h["hazard"] for h in hits)),
                "rear_ended": int(any(h.get("ego_side") == "rear" for h in hits)),
            }
        )
        per[spec.scenario] += 1
    return rows


def summarise(rows: list[dict], paper_trials: int) -> dict:
    """Per policy (seeds pooled): avoidance % with its interval and mean injury (-ISS, both units), per scenario
    and overall, on every trial and on the first ``paper_trials`` per scenario."""
    out: dict = {"policies": {}}
    for policy in dict.fromkeys(r["policy"] for r in rows):
        mine = [r for r in rows if r["policy"] == policy]
        s: dict = {"seeds": sorted({r["policy_seed"] for r in mine})}
        for label, subset in (("all", mine), ("paper", [r for r in mine if r["trial"] < paper_trials])):
            cells = {}
            for scenario in (*SCENARIOS, "overall"):
                at = subset if scenario == "overall" else [r for r in subset if r["scenario"] == scenario]
                k, n = sum(r["avoided"] for r in at), len(at)
                cells[scenario] = {
                    "n": n,
                    "avoidance": 100 * k / n if n else None,
                    "interval": wilson(k, n),
                    "injury_kmh": -float(np.mean([r["iss_kmh"] for r in at])) if n else None,
                    "injury_ms": -float(np.mean([r["iss_ms"] for r in at])) if n else None,
                    "rear_ended": 100 * float(np.mean([r["rear_ended"] for r in at])) if n else None,
                }
            s[label] = cells
        out["policies"][policy] = s
    names = list(out["policies"])
    tests = {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            ra = sorted(
                (r for r in rows if r["policy"] == a), key=lambda r: (r["policy_seed"], r["scenario"], r["trial"])
            )
            rb = sorted(
                (r for r in rows if r["policy"] == b), key=lambda r: (r["policy_seed"], r["scenario"], r["trial"])
            )
            xa = _per_trial(ra)
            xb = _per_trial(rb)
            keys = sorted(set(xa) & set(xb))
            if keys:
                tests[f"{a} vs {b}"] = paired_permutation_p([xa[k] for k in keys], [xb[k] for k in keys])
    out["paired_p"] = tests
    return out


def _per_trial(rows: list[dict]) -> dict:
    """Mean ISS (km/h) per (scenario, trial), over a policy's seeds."""
    acc: dict = {}
    for r in rows:
        acc.setdefault((r["scenario"], r["trial"]), []).append(r["iss_kmh"])
    return {k: float(np.mean(v)) for k, v in acc.items()}


def tables(summary: dict, trials: int, paper_trials: int) -> str:
    pol = summary["policies"]
    head = "| policy | right | left | left turn | overall | right | left | left turn | overall |"
    rule = "|---|" + "---:|" * 8

    def fmt(v, f="{:.1f}"):
        return "–" if v is None else f.format(v)

    lines = [
        "# Kim et al. on family kim (seeds pooled): Table 2's layout",
        "",
        f"## The paper's size: the first {paper_trials} trials per scenario",
        "",
        "Avoidance % (no collision of any kind) | mean injury (minus the summed Sobhani ISS per episode, ΔV in km/h)",
        "",
        head,
        rule,
    ]
    for name, (avoid, injury) in PAPER_TABLE_2.items():
        lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in (*avoid, *injury)) + " |")
    for name, s in pol.items():
        c = s["paper"]
        cells = [fmt(c[k]["avoidance"]) for k in (*SCENARIOS, "overall")]
        cells += [fmt(c[k]["injury_kmh"], "{:.2f}") for k in (*SCENARIOS, "overall")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "The paper's inconsistencies (docs/design.md §10): its 'all' column is not the mean of the three scenarios, "
        "and 87.00 / 31.50 / 5.30 are not multiples of 1/30; its human row is a driving-simulator study, not "
        "reproduced here.",
        "",
        f"## {trials} trials per scenario, with 95 % Wilson intervals",
        "",
        "| policy | seeds | right | left | left turn | overall | injury (km/h) | injury (m/s) | rear-ended % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, s in pol.items():
        c = s["all"]
        cells = [
            f"{c[k]['avoidance']:.1f} [{c[k]['interval'][0]:.0f}, {c[k]['interval'][1]:.0f}]"
            for k in (*SCENARIOS, "overall")
        ]
        o = c["overall"]
        lines.append(
            f"| {name} | {','.join(map(str, s['seeds']))} | "
            + " | ".join(cells)
            + f" | {o['injury_kmh']:.2f} | {o['injury_ms']:.2f} | {o['rear_ended']:.1f} |"
        )
    lines += ["", "## Pairwise tests (paired sign-flip permutation test on per-trial ISS, 10,000 flips)", ""]
    lines += ["| pair | p |", "|---|---:|"]
    lines += [f"| {pair} | {p:.4f} |" for pair, p in summary["paired_p"].items()]
    lines.append("")
    return "\n".join(lines)


def figure(summary: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pol = summary["policies"]
    names = list(pol)
    groups = (*SCENARIOS, "overall")
    fig, ax = plt.subplots(figsize=(8, 3.6))
    width = 0.8 / max(1, len(names))
    for i, name in enumerate(names):
        c = pol[name]["all"]
        vals = [c[g]["avoidance"] for g in groups]
        lo = [v - c[g]["interval"][0] for g, v in zip(groups, vals, strict=True)]
        hi = [c[g]["interval"][1] - v for g, v in zip(groups, vals, strict=True)]
        ax.bar(np.arange(len(groups)) + i * width, vals, width, yerr=[lo, hi], capsize=2, label=name)
    ax.set_xticks(np.arange(len(groups)) + 0.4 - width / 2, [g.replace("_", " ") for g in groups])
    ax.set_ylabel("runner avoided, no collision (%)")
    ax.set_ylim(0, 105)
    ax.axhline(87.83, color="k", ls=":", lw=1)
    ax.text(len(groups) - 0.5, 88.5, "paper's goal-unaware DDPG, overall", ha="right", fontsize=7)
    ax.legend(fontsize=7, ncol=2, loc="lower left")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def render_tables(rows: list[dict], settings: dict) -> str:
    """The evaluation's tables from its rows and ``summary["render"]``."""
    paper_trials = int(settings["paper_trials"])
    return tables(summarise(rows, paper_trials), int(settings["trials"]), paper_trials)


def ncap_policies(cfg) -> list[tuple]:
    """AEB-3m and every goal-unaware LIDAR agent on the NCAP bank. A camera agent of the family (agent=ddpg_wm_kim)
    acts at the world model's 1/15 s steps, not at this group's 0.1 s, and is left out (logged)."""
    from envs.kim import Aeb3m

    out = [(Aeb3m(), 0, False, True)]
    for agent in artifacts.trained_agents(cfg, family=FAMILY):
        if agent.reward not in GOAL_REWARDS:
            policy, camera = load_policy(cfg, agent)
            if camera:
                log.info("[ncap] %s: a camera agent of family kim; not run in the 0.1 s kim group", agent.key)
                continue
            out.append((policy, agent.seed, False, True))
    return out


def draw_suffix(c) -> str:
    """What sets this bank apart from the middle of the flank, for its directory's name (after the bank's own,
    ``artifacts.eval_dir``), so that another placement (``_at+2.25``, ``_spread2.25``) never overwrites it."""
    suffix = ""
    if float(c.impact_offset):
        suffix += f"_at{float(c.impact_offset):+g}"
    if float(c.impact_offset_spread):
        suffix += f"_spread{float(c.impact_offset_spread):g}"
    return suffix


def evaluate(cfg) -> dict:
    """``evaluate.family=kim``: AEB-3m, braking, the planner, every LIDAR and world-model agent of the family and
    (``evaluate.kim.world_model_agents``) the paper's street-trained agents, on the same seeded trials."""
    from ..policies import porav_policies
    from ..training import tensorboard

    c = drawn(cfg, "kim")
    out = artifacts.eval_dir(cfg)
    out = out.with_name(out.name + draw_suffix(c))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    specs = bank(c)
    agents = artifacts.trained_agents(cfg, family="kim")
    record = artifacts.provenance(cfg, "eval")
    loaded = [(a, *load_policy(cfg, a)) for a in agents]  # fail fast, before any trial runs
    lidar = [(p, a.seed) for a, p, camera in loaded if not camera]
    camera = [(p, a.seed) for a, p, camera in loaded if camera]
    if c.world_model_agents:  # the paper's agents, trained on the street, at the junction as they are
        camera += [(p, s) for p, s, sees, _ in porav_policies(cfg) if sees]
    env = family_env(cfg, "kim_unaware")
    rows = []
    for policy in scripted(cfg):
        rows += run_policy(env, policy, specs)
    for policy, seed in lidar:
        rows += run_policy(env, policy, specs, seed)
    env.close()
    if camera:  # world-model agents act at the step length their world model was trained with
        env = family_env(cfg, "kim_unaware", camera=True, step_s=world_model_step_s(cfg))
        for policy, seed in camera:
            rows += run_policy(env, policy, specs, seed)
        env.close()
    if not agents:
        log.info(
            "[eval kim] no kim agents under %s. Train one with `python -m worldmodel.train_agent experiment=%s "
            "agent=ddpg_kim` (LIDAR) or agent=ddpg_wm_kim (camera).",
            artifacts.runs_root(cfg),
            cfg.experiment,
        )
    write_rows(out, rows, COLUMNS)
    summary = summarise(rows, int(c.paper_trials))
    summary["render"] = {"trials": int(c.trials), "paper_trials": int(c.paper_trials)}  # what tables() is given
    (out / "tables.md").write_text(tables(summary, int(c.trials), int(c.paper_trials)))
    figure(summary, out / "avoidance.png")
    writer = tensorboard(out)
    for policy, s in summary["policies"].items():
        writer.add_scalar(f"kim/{policy}/avoidance", s["all"]["overall"]["avoidance"], 0)
    writer.close()
    headline = {p: f"avoidance {s['all']['overall']['avoidance']:.1f} %" for p, s in summary["policies"].items()}
    record_if_test(cfg, "kim", rows, record, headline)
    seal(out, summary, record, t0)
    log.info(
        "[eval kim] %d trials x %d policies in %.0f s: %s",
        len(specs),
        len(c.policies) + len(lidar) + len(camera),
        summary["wall_s"],
        out / "tables.md",
    )
    return summary
