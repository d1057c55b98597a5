"""Merola et al. 2022 on our simulator: Double DQN on camera frames in three pre-accident scenarios (family ``merola``).

    python -m worldmodel.train_agent experiment=NAME agent=ddqn_merola [seed=K] [obs=frames_resnet]
    python -m worldmodel.evaluate experiment=NAME evaluate.family=merola

Training (``train_agent`` with ``agent.variant=ddqn_merola``): ``agent.merola.total_steps`` steps (whole episodes) drawn
from
``envs.merola.sample`` (lead car braking, junction crossing, oncoming drift; 60 steps of 0.1 s), reward ``merola``,
nine actions {brake, none, throttle} × {left, straight, right} (pedal -1 / 0 / +1, steer -0.5 / 0 / +0.5), Double
DQN from ``worldmodel/models/dqn.py`` with one update per step. The observation (a deviation, docs/design.md
§10: our camera gives class maps, not RGB, and ImageNet weights are not at hand):

* ``frames_vae`` (default): the frozen VAE's means of the last 4 frames (4 × 128), the first frame repeated at the
  start of an episode;
* ``frames_resnet``: the last 4 frames, coloured, through a frozen ResNet-18 (``worldmodel/models/resnet.py``)
  whose weights the user supplies (``agent.merola.resnet_weights``); the 2×2×512 maps of the 4 frames are concatenated;
* ``privileged``: the true state (``TrueStateView``), no camera: the diagnosis that separates the learner from
  what the frames show.

Runs: ``runs/NAME/agent_merola_ddqn_merola[-OBS]/seedK/`` with ``last.pt`` (network, optimiser, replay, RNG,
episode) every ``CHECKPOINT_EPISODES``, TensorBoard and ``metrics.json`` with the learning curve.

Evaluation (``evaluate.family=merola``): per scenario, ``evaluate.merola.trials`` seeded trials shared by every
policy: collision rate (Wilson 95 %), mean ego Δv, the occupant's Joksch risk and the pedestrian's Rosén risk
(``envs/injury.py``), and the return. Policies: straight-line braking from the start (every episode here holds a
hazard, so braking at once is a strong floor on collisions, and one the reward discourages), Kim's AEB-3m (hold
speed, brake once something is within 3 m ahead), the privileged planner, the
paper's world-model agents of the experiment (R1 / R2 DDPG and the chooser, at their own 1/15 s steps, acting from
the start), and every ``ddqn_merola`` agent. Writes ``runs/NAME/eval_merola/``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque

import numpy as np
import torch

from envs.merola import SCENARIOS, MerolaSpec
from envs.merola import sample as sample_merola
from envs.streams import MEROLA_TRAINING_EPISODES

from ... import artifacts, loading
from ...artifacts import AgentId
from ...common import StageError, decision_device, make_env, percent, resolve_device
from ...learners.dqn import DQNLearner
from ...learners.loop import Callbacks, TrainingLoop
from ...stats import wilson
from ..common import (
    DQNEpisodes,
    DQNPolicy,
    Driven,
    TrueStateView,
    dqn_checkpoint,
    dqn_config,
    evaluation,
    resume_dqn,
    world_model_step_s,
)
from . import FAMILY as DECLARED

log = logging.getLogger(__name__)
FAMILY, PRESET = DECLARED.name, DECLARED.preset  # as the package declares them
NCAP_REWARD = "merola"  # the reward its env reports on the Euro NCAP bank
PEDALS, STEERS = (-1.0, 0.0, 1.0), (-0.5, 0.0, 0.5)
ACTIONS = np.array([(s, p) for p in PEDALS for s in STEERS], dtype=np.float32)  # index -> [steer, pedal]
FRAMES = 4
ROLLING = 100
CHECKPOINT_EPISODES = 100
PAPER_PLATEAU = -10.0  # Merola et al. Fig. 4: the rolling-100 return stays near -10 after ~6,000 episodes
OBSERVATIONS = ("frames_vae", "frames_resnet", "privileged")


def merola_action(index: int) -> np.ndarray:
    """Action ``index`` of the nine as our [steer, pedal]."""
    return ACTIONS[int(index)]


# ----------------------------------------------------------------------------- what the agent sees
class FrameStack:
    """The features of the last ``FRAMES`` camera frames, oldest first; the first frame fills the stack."""

    camera = True

    def __init__(self, features, per_frame: int):
        self.features, self.per_frame = features, int(per_frame)
        self.dim = FRAMES * self.per_frame
        self.frames: deque = deque(maxlen=FRAMES)

    def reset(self, seed: int | None = None) -> None:
        self.frames.clear()

    def __call__(self, env, obs) -> np.ndarray:
        f = self.features(np.asarray(obs["seg"]))
        if not self.frames:
            self.frames.extend([f] * FRAMES)
        else:
            self.frames.append(f)
        return np.concatenate(self.frames).astype(np.float32)

    def note_action(self, action) -> None:
        pass


def vae_features(vae):
    def features(seg: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return vae.encode(torch.from_numpy(seg.astype(np.int64))[None])[0][0].numpy()

    return features


def resnet_features(net):
    from envs.camera import colorize

    from ...models.resnet import IMAGENET_MEAN, IMAGENET_STD

    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)

    def features(seg: np.ndarray) -> np.ndarray:
        rgb = torch.from_numpy(colorize(seg)).permute(2, 0, 1)[None].float() / 255.0
        with torch.inference_mode():
            return net((rgb - mean) / std).reshape(-1).numpy()

    return features


def observer(cfg, obs: str) -> FrameStack | TrueStateView:
    if obs not in OBSERVATIONS:
        raise StageError(f"agent.obs={obs}: ddqn_merola sees one of {', '.join(OBSERVATIONS)}")
    if obs == "privileged":
        return TrueStateView()
    if obs == "frames_resnet":
        from ...models.resnet import load_resnet18

        net = load_resnet18(cfg.agent.merola.resnet_weights)
        with torch.inference_mode():
            per_frame = net(torch.zeros(1, 3, 64, 64)).numel()
        return FrameStack(resnet_features(net), per_frame)
    vae, _ = loading.load_vae(cfg, "best")
    return FrameStack(vae_features(vae), int(vae.latent_dim))


def family_env(cfg, step_s: float | None = None, camera: bool = True, reward: str = "merola"):
    options = {} if step_s is None else {"step_s": step_s}
    return make_env(cfg, camera=camera, family="merola", reward=reward, **options)


# ----------------------------------------------------------------------------- training
def episode_scenario(seed: int, episode: int) -> MerolaSpec:
    """Training episode ``episode``'s scenario: a function of (seed, episode) only, so a resumed run draws what an
    uninterrupted one would."""
    return sample_merola(np.random.default_rng([int(seed), MEROLA_TRAINING_EPISODES, int(episode)]))


def train(cfg, run_, agent_id: AgentId) -> dict:
    """``train_agent`` for ``agent.variant=ddqn_merola``: episodes of family merola until ``agent.merola.total_steps``
    steps have been taken; the learning rate decays over exactly that many updates."""
    from ...config import validate

    if agent_id.reward not in DECLARED.rewards:
        raise StageError(
            f"ddqn_merola learns with reward {' or '.join(DECLARED.rewards)}, not {agent_id.reward}: use "
            "agent=ddqn_merola"
        )
    typed = validate(cfg)
    if typed.agent.learner == "counterfactual":  # agent=counterfactual_merola
        from . import counterfactual

        return counterfactual.train(cfg, run_, agent_id, typed)
    return MerolaRun(cfg, typed, run_, agent_id).train()


class MerolaRun(Callbacks):
    """One ddqn_merola run: its learner (no trauma memory), frame-stack view and env, and the learning curve."""

    def __init__(self, cfg, typed, run_, agent_id: AgentId):
        """``typed``: ``cfg`` validated."""
        from ...models.dqn import DQN

        self.typed, self.run_, self.agent_id = typed, run_, agent_id
        self.total = total = typed.agent.merola.total_steps
        self.see = see = observer(cfg, typed.agent.obs)
        self.env = family_env(cfg, camera=see.camera, reward=agent_id.reward)
        self.hp = dataclasses.replace(dqn_config(cfg), total_steps=total)
        agent = DQN(see.dim, len(ACTIONS), self.hp, typed.seed, device=resolve_device(typed.device))
        self.learner = DQNLearner(agent)
        episode, self.curve = resume_dqn(run_, self.learner, see.dim, {"return": [], "collision": [], "scenario": []})
        self.recent: deque = deque(self.curve["return"][-ROLLING:], maxlen=ROLLING)
        self.crashes: deque = deque(self.curve["collision"][-ROLLING:], maxlen=ROLLING)
        episodes = DQNEpisodes(self.env, see, lambda k: (episode_scenario(typed.seed, k), None), merola_action)
        self.loop = TrainingLoop(self.learner, episodes, run_, self, episode=episode)

    def snapshot(self) -> None:
        obs, dim, loop = self.typed.agent.obs, self.see.dim, self.loop
        reward = self.agent_id.reward
        self.run_.save(dqn_checkpoint(self.learner, self.hp, loop.episode, self.curve, obs, dim, reward, family=FAMILY))

    def on_episode(self, loop, o: dict, ret: float, length: int) -> None:
        crashed = bool(o["vehicle_collision"] or o["static_collision"] or o["pedestrian_collision"])
        self.curve["return"].append(float(ret))
        self.curve["collision"].append(int(crashed))
        self.curve["scenario"].append(self.env.scenario.scenario)
        self.recent.append(float(ret))
        self.crashes.append(int(crashed))
        writer, episode = self.run_.writer, loop.episode
        writer.add_scalar("episode/return", ret, episode)
        writer.add_scalar("episode/return_rolling", float(np.mean(self.recent)), episode)
        writer.add_scalar("episode/collision_rate_rolling", float(np.mean(self.crashes)), episode)
        writer.add_scalar("train/epsilon", self.learner.agent.epsilon(), episode)
        if "loss" in loop.losses:
            writer.add_scalar("train/loss", loop.losses["loss"], episode)
        if episode % CHECKPOINT_EPISODES == 0:
            self.snapshot()

    def train(self) -> dict:
        from tqdm import tqdm

        run_, loop = self.run_, self.loop
        run_.restore_random_state()  # building the networks and views drew from them
        with tqdm(
            total=self.total, initial=loop.step, desc=f"ddqn merola ({self.typed.agent.obs})", unit="step"
        ) as bar:
            loop.run(lambda: loop.step >= self.total, bar)
        self.snapshot()
        self.env.close()
        if run_.stop.requested:
            return run_.stopped(loop.step)
        return {
            "reward": self.agent_id.reward,
            "obs": self.typed.agent.obs,
            "episodes": loop.episode,
            "steps": loop.step,
            "recent_return": float(np.mean(self.recent)) if self.recent else None,
            "recent_collision_rate": float(np.mean(self.crashes)) if self.crashes else None,
            "curve": self.curve,
        }


def summary(metrics: dict) -> str:
    if metrics.get("learner") == "counterfactual":
        last = metrics["history"].get(f"actor{len(metrics.get('labelled_episodes', {})) - 1}", {})
        return f"{metrics.get('labelled_states', 0)} labelled states; held out: {last}"
    ret = metrics["recent_return"]
    return (
        f"{metrics['episodes']} episodes; last 100: return {'n/a' if ret is None else f'{ret:.1f}'}, "
        f"collisions {percent(metrics['recent_collision_rate'])}"
    )


def load_policy(cfg, agent_id: AgentId):
    """A trained agent of the family, greedy, with the hyperparameters and observation it was trained with: a
    ``DQNPolicy`` (agent=ddqn_merola), or a ``ShiftPolicy`` (agent=counterfactual_merola)."""
    from ...models.dqn import DQN, DQNConfig

    state = loading.load_agent_state(cfg, agent_id, "last")
    if state.get("family") != "merola":
        raise StageError(f"{agent_id.dir(cfg)} is not a merola agent; move it out of {artifacts.runs_root(cfg)}")
    if state.get("learner") == "counterfactual":
        from .counterfactual import policy

        out = policy(cfg, state, agent_id.policy)
        out.policy_seed = agent_id.seed
        return out
    see = observer(cfg, state["obs"])
    if see.dim != state["obs_dim"]:
        raise StageError(
            f"{agent_id.dir(cfg)} was trained on inputs of size {state['obs_dim']}, the observation {state['obs']} "
            f"gives {see.dim} (the VAE changed?); retrain it with "
            f"`python -m worldmodel.train_agent experiment={cfg.experiment} agent=ddqn_merola seed={agent_id.seed}`"
        )
    agent = DQN(see.dim, len(ACTIONS), DQNConfig(**state["dqn_config"]), agent_id.seed, device=decision_device(cfg))
    agent.load_state_dict(state["agent"])
    return DQNPolicy(agent_id.policy, agent, see, agent_id.seed, merola_action)


# ----------------------------------------------------------------------------- evaluation
def bank(c) -> list[MerolaSpec]:
    """``c.trials`` seeded trials per scenario, the same for every policy (``c``: the typed ``evaluate.merola``, or
    anything with an int ``seed`` and ``trials``)."""
    out = []
    for k, scenario in enumerate(SCENARIOS):
        rng = np.random.default_rng([c.seed, k])
        out += [sample_merola(rng, scenario) for _ in range(c.trials)]
    return out


COLUMNS = (
    "policy",
    "policy_seed",
    "group",
    "scenario",
    "ego_speed",
    "other_speed",
    "ttc",
    "collision",
    "first_crash",
    "delta_v_ego",
    "occupant_injury",
    "pedestrian_injury",
    "return_merola",
    "lane_departure",
)


def run_policy(env, policy, specs, group: str, policy_seed: int = 0) -> list[dict]:
    from tqdm import tqdm

    from envs.rollout import rollout

    rows = []
    for spec in tqdm(specs, desc=policy.name, unit="trial"):
        o = rollout(env, policy, spec).outcome
        hits = [h for h in env.collisions if h["kind"] != "pedestrian"]
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": policy_seed,
                "group": group,
                "scenario": spec.scenario,
                "ego_speed": spec.ego_speed,
                "other_speed": spec.other_speed,
                "ttc": spec.ttc,
                "collision": int(bool(env.collisions)),
                "first_crash": env.collisions[0]["class"] if env.collisions else "",
                "delta_v_ego": float(hits[0]["delta_v_ego"]) if hits else 0.0,
                "occupant_injury": o["occupant_injury"],
                "pedestrian_injury": o["pedestrian_injury"],
                "return_merola": o["return_merola"],
                "lane_departure": o["lane_departure"],
            }
        )
    return rows


def summarise(rows: list[dict]) -> dict:
    """Per policy (seeds pooled) and scenario: collision rate with its Wilson interval, mean ego Δv over all trials
    and over the collisions, mean Joksch and Rosén risk, mean return; and the paired difference in collisions
    against braking."""
    out: dict = {}
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    for name in policies:
        mine = [r for r in rows if r["policy"] == name]
        per: dict = {}
        for scenario in (*SCENARIOS, "all"):
            sel = [r for r in mine if scenario == "all" or r["scenario"] == scenario]
            k, n = sum(r["collision"] for r in sel), len(sel)
            dv = [r["delta_v_ego"] for r in sel if r["collision"]]
            per[scenario] = {
                "trials": n,
                "collision_rate": 100 * k / n if n else math.nan,
                "collision_ci": wilson(k, n),
                "delta_v_ego": float(np.mean([r["delta_v_ego"] for r in sel])) if sel else math.nan,
                "delta_v_ego_crashes": float(np.mean(dv)) if dv else math.nan,
                "joksch": 100 * float(np.mean([r["occupant_injury"] for r in sel])) if sel else math.nan,
                "rosen": 100 * float(np.mean([r["pedestrian_injury"] for r in sel])) if sel else math.nan,
                "return": float(np.mean([r["return_merola"] for r in sel])) if sel else math.nan,
                "lane_departure": 100 * float(np.mean([r["lane_departure"] for r in sel])) if sel else math.nan,
            }
        out[name] = {"group": mine[0]["group"], "seeds": sorted({r["policy_seed"] for r in mine}), "scenarios": per}
    return {"policies": out, "scenarios": list(SCENARIOS)}


def tables(summary: dict, trials: int) -> str:
    lines = [
        f"# Merola et al.'s scenarios, {trials} seeded trials per scenario (the same for every policy)",
        "",
        "Collision rate % [Wilson 95 %] per scenario; Δv: the ego's velocity change in its first crash, mean over "
        "all trials (km/h); Joksch: the occupants' severe-injury risk, mean over all trials (%); return: reward "
        "merola per episode (the paper's learning curve plateaus near -10 with unpublished thresholds, so compare "
        "collisions and Δv, not returns). Seeds of one agent are pooled.",
        "",
        "| policy | " + " | ".join(f"{s} coll. %" for s in (*SCENARIOS, "all")) + " | Δv km/h | Joksch % | return |",
        "|---|" + "---:|" * (len(SCENARIOS) + 4),
    ]
    for name, s in summary["policies"].items():
        cells = []
        for scenario in (*SCENARIOS, "all"):
            p = s["scenarios"][scenario]
            lo, hi = p["collision_ci"]
            cells.append(f"{p['collision_rate']:.1f} [{lo:.0f}, {hi:.0f}]")
        a = s["scenarios"]["all"]
        cells += [f"{3.6 * a['delta_v_ego']:.1f}", f"{a['joksch']:.2f}", f"{a['return']:.1f}"]
        label = name + (f" (seeds {', '.join(map(str, s['seeds']))})" if len(s["seeds"]) > 1 else "")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Rosén pedestrian risk is 0 for every policy: the family has no pedestrians (the column stays in "
        "`summary.json` for the shared layout).",
    ]
    return "\n".join(lines) + "\n"


def figure(summary: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary["policies"])
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(names) + 2), 3.6))
    width = 0.8 / len(SCENARIOS)
    for k, scenario in enumerate(SCENARIOS):
        rates = [summary["policies"][n]["scenarios"][scenario]["collision_rate"] for n in names]
        ci = [summary["policies"][n]["scenarios"][scenario]["collision_ci"] for n in names]
        lo = [max(0.0, r - c[0]) for r, c in zip(rates, ci, strict=True)]  # Wilson's bound at 0 % is 0 up to rounding
        hi = [max(0.0, c[1] - r) for r, c in zip(rates, ci, strict=True)]
        ax.bar(np.arange(len(names)) + (k - 1) * width, rates, width, yerr=[lo, hi], capsize=2, label=scenario)
    ax.set_xticks(np.arange(len(names)))
    ax.set_xticklabels(names, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("collision rate, % (95 % CI)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8)
    ax.set_title("Merola et al.'s scenarios: lower is better")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def learning_curves(cfg, agents: list[AgentId], path) -> None:
    """Rolling-100 return of every ddqn_merola run beside the paper's plateau (Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.4))
    for agent in agents:
        state = loading.load_agent_state(cfg, agent, "last")
        if "curve" not in state:
            continue  # agent=counterfactual_merola: no episodes of its own to plot
        curve = state["curve"]["return"]
        if len(curve) >= ROLLING:
            rolling = np.convolve(curve, np.ones(ROLLING) / ROLLING, mode="valid")
            ax.plot(np.arange(ROLLING, len(curve) + 1), rolling, label=agent.key, lw=1)
    ax.axhline(PAPER_PLATEAU, color="k", ls="--", lw=1, label="paper's plateau (~-10)")
    ax.set_xlabel("episode")
    ax.set_ylabel("return, rolling 100")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def render_tables(rows: list[dict], settings: dict) -> str:
    """The evaluation's tables from its rows and ``summary["render"]``."""
    return tables(summarise(rows), int(settings["trials"]))


def ncap_policies(cfg) -> list[tuple]:
    """Every ddqn_merola agent on the NCAP bank (camera frames: the car-to-car tests too). The counterfactual-cost
    learner (agent=counterfactual_merola) is left out (logged): it decides in its first steps, and this group acts
    from the start of each test, so it would only show braking from there."""
    from envs.counterfactual import ShiftPolicy

    out = []
    for agent in artifacts.trained_agents(cfg, family=FAMILY):
        policy = load_policy(cfg, agent)
        if isinstance(policy, ShiftPolicy):
            log.info("[ncap] %s: a takeover policy, not run from the start of the tests", agent.key)
            continue
        out.append((policy, agent.seed, True, True))
    return out


def scripted(cfg) -> list:
    """Straight-line braking from the start, AEB-3m and the privileged planner (minimising R2's injury cost); and,
    to read the reward against, driving on (``hold``) and braking that lets go below v_min (``brake_release``) or
    at a standstill (``brake_stop``)."""
    from envs import StraightLineBraking
    from envs.kim import Aeb3m
    from envs.merola import BrakeThenRelease, BrakeToStandstill, Hold
    from envs.planner import PrivilegedPlanner

    from ...config import oracle_settings

    make = {
        "braking": StraightLineBraking,
        "aeb3m": Aeb3m,
        "hold": Hold,
        "brake_release": BrakeThenRelease,
        "brake_stop": BrakeToStandstill,
        "oracle": lambda: PrivilegedPlanner.from_settings(**{**oracle_settings(cfg), "step_s": 0.1}),
    }
    return [make[name]() for name in cfg.evaluate.merola.policies]


def evaluate(cfg) -> dict:
    """``evaluate.family=merola``: braking, the planner, the paper's world-model agents and every ddqn_merola agent
    on the same seeded trials."""
    return evaluation(cfg, FAMILY, COLUMNS, drive, report, PRESET)


def drive(cfg, c) -> Driven:
    """The scripted policies without the camera, the ddqn agents at 0.1 s, the paper's agents at their own steps."""
    from ...config import validate
    from ...policies import porav_policies

    typed = validate(cfg)
    specs = bank(c)
    agents = artifacts.trained_agents(cfg, family="merola")
    learned = [load_policy(cfg, a) for a in agents]  # fail fast, before any trial runs
    world_model = [(p, s) for p, s, camera, _ in porav_policies(cfg) if camera] if c.world_model_agents else []
    rows = []
    env = family_env(cfg, step_s=0.1, camera=False)
    for policy in scripted(cfg):
        rows += run_policy(env, policy, specs, "scripted")
    env.close()
    env = family_env(cfg, step_s=0.1)
    for policy in learned:
        group = "counterfactual" if hasattr(policy, "steps") else "ddqn_merola"  # a ShiftPolicy decides at steps
        rows += run_policy(env, policy, specs, group, policy.policy_seed)
    env.close()
    if world_model:  # the paper's agents act at the step length they were trained with
        env = family_env(cfg, step_s=world_model_step_s(typed))
        for policy, seed in world_model:
            rows += run_policy(env, policy, specs, "world model", seed)
        env.close()
    return Driven(rows, agents, len(specs), len({(r["policy"], r["policy_seed"]) for r in rows}))


def report(cfg, c, done: Driven, out) -> tuple[dict, dict]:
    """The collision, delta-v, risk and return table per scenario, its figure and the learning curves."""
    from ...training import tensorboard

    summary = summarise(done.rows)
    summary["render"] = {"trials": c.trials}  # what tables() is given
    (out / "tables.md").write_text(tables(summary, c.trials))
    figure(summary, out / "collisions.png")
    if done.agents:
        learning_curves(cfg, done.agents, out / "learning_curves.png")
    writer = tensorboard(out)
    for name, s in summary["policies"].items():
        writer.add_scalar(f"merola/{name}/collision_rate", s["scenarios"]["all"]["collision_rate"], 0)
    writer.close()
    headline = {
        p: f"collisions {s['scenarios']['all']['collision_rate']:.1f} %" for p, s in summary["policies"].items()
    }
    return summary, headline


def ncap_group(cfg, takeover_ttc_s: float) -> tuple:
    """Its agents drive from the test's start, at Merola's 0.1 s steps."""
    return 0.1, ncap_policies(cfg), NCAP_REWARD, None
