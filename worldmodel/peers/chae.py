"""Chae et al. 2017 on our simulator: DQN braking with a trauma memory, trained and evaluated on family ``chae``.

    python -m worldmodel.train_agent experiment=NAME agent=dqn_chae [seed=K] [obs=worldmodel]
    python -m worldmodel.evaluate experiment=NAME evaluate.family=chae

Training (``train_agent`` with ``agent.learner=dqn``): ``agent.episodes`` episodes drawn from the paper's distribution
(``envs.chae.sample_chae``: Scenario 1 or 2, TTC ~ U(1.5, 4) s, 10-60 km/h), 0.1 s steps, Chae's four brake levels
and reward Eq. 8; ``worldmodel/models/dqn.py`` learns from one update per step. A transition into a bump is a
trauma. The observation is Chae's 15-value pedestrian history (``agent.obs=pedestrian_history``, the paper's,
privileged: it reads the simulator as their perception module would deliver it) or our world model's
[z, zhat, speed] from the camera (``obs=worldmodel``). Runs: ``runs/NAME/agent_chae_dqn_chae[-worldmodel]/seedK/``
with ``last.pt`` (network, optimiser, both memories, RNG, episode) every ``checkpoint_every_episodes``, TensorBoard
(return, bump rate, ends, loss, epsilon) and ``metrics.json`` with the learning curve.

Evaluation (``evaluate.family=chae``): Table I's layout, Scenario-1 bump rate at each TTC of ``evaluate.chae.ttcs``
over ``evaluate.chae.trials`` seeded trials (the same scenarios for every policy), Scenario 2's unnecessary stops,
the stopping distance to the pedestrian (their Fig. 7), and, since "bump" is only Chae's proxy, footprint contact,
impact speed and Rosen pedestrian injury. Policies: straight-line braking from the pedestrian's start, TTC-threshold
braking, the privileged latest-safe braking, a hand-written closing-speed rule on the agent's own noisy state
(``closing_braking``, not privileged; ``evaluate.chae.policies`` picks among these four), every dqn agent of the
experiment and, with ``evaluate.chae.ensemble`` k, the greedy mean-Q ensemble of each k consecutive seeds of a
variant. Writes ``runs/NAME/eval_chae/``.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from types import SimpleNamespace

import numpy as np

from envs.chae import (
    BRAKE_LEVELS,
    SAFETY_LINE_M,
    STEP_S,
    TTC_RANGE,
    V_INIT_RANGE,
    V_PED_RANGE,
    BrakeAtTrigger,
    ChaeSpec,
    ClosingSpeedBraking,
    LatestSafeBraking,
    PedestrianHistory,
    brake_action,
    sample_chae,
)
from envs.streams import CHAE_BANK_SCENARIO_2, CHAE_TRAINING_EPISODES

from .. import artifacts
from ..artifacts import AgentId
from ..common import StageError, atomic_torch_save, atomic_write_bytes, make_env
from .common import DQNPolicy, dqn_checkpoint, dqn_config, drawn, record_if_test, resume_dqn, seal, write_rows

log = logging.getLogger(__name__)
FAMILY, PRESET, NCAP_REWARD = "chae", "dqn_chae", "chae"  # the Peer interface (worldmodel/peers/__init__.py)
# Chae's state to roughly unit scale: dx up to ~85 m, dy up to ~6 m, speed up to ~17 m/s
HISTORY_SCALE = np.tile(np.array([1 / 50.0, 1 / 4.0, 1 / 20.0], np.float32), PedestrianHistory.steps)
PAPER_TABLE_I = {0.9: 61.29, 1.1: 18.85, 1.3: 0.74}  # bump rate, %; 0 from 1.5 s on (10,000 trials per TTC)
PHYSICS_BAND = {
    0.9: (37.3, 76.5),
    1.1: (3.1, 12.1),
    1.3: (0.0, 0.46),
    1.5: (0.0, 0.0),
}  # brake at the trigger .. 0.1 s late
# What a reproduction must reach (docs/design.md §10): the paper's Table I has no bumps from 1.5 s on, and its
# agent brakes only when it must; we ask for bumps in at most 1 % of the trials at every TTC from 1.5 s and
# needless stops in at most 5 % of Scenario 2's, judged for each run (or ensemble) on its own.
BAR_FROM_TTC, BAR_BUMP, BAR_STOPS = 1.5, 1.0, 5.0
ROLLING = 100
CHECKPOINT_EPISODES = 100


# ----------------------------------------------------------------------------- what the agent sees
class HistoryObserver:
    """Chae's 15-value pedestrian history, scaled (privileged; no camera)."""

    camera = False
    dim = PedestrianHistory.dim

    def __init__(self, noise_m: float = 0.1):
        self.view = PedestrianHistory(noise_m)

    def reset(self, seed: int | None) -> None:
        self.view.reset(seed)

    def __call__(self, env, obs) -> np.ndarray:
        return self.view(env) * HISTORY_SCALE

    def note_action(self, action) -> None:
        pass


class WorldModelObserver:
    """The world model's agent input from the camera frame (``agent_obs.WorldModelEncoder``)."""

    camera = True

    def __init__(self, encoder):
        self.encoder, self.dim = encoder, encoder.dim

    def reset(self, seed: int | None) -> None:
        self.encoder.reset()

    def __call__(self, env, obs) -> np.ndarray:
        return self.encoder.encode(obs)

    def note_action(self, action) -> None:
        self.encoder.note_action(action)


def observer(cfg, obs: str, noise_m: float | None = None):
    """What a dqn agent sees; Chae's state with ``noise_m`` (default: ``agent.chae_noise_m``, training's)."""
    if obs == "pedestrian_history":
        return HistoryObserver(float(cfg.agent.chae_noise_m) if noise_m is None else noise_m)
    return WorldModelObserver(artifacts.load_world_model(cfg, use_speed=True, frame_view=False))


def family_env(cfg, camera: bool, end_on_bump: bool = True):
    """Family chae's env at the paper's 0.1 s steps, whatever ``env.step_s`` the stage was given (``evaluate
    evaluate.family=chae`` does not load the agent preset that sets it); ``end_on_bump=False`` (evaluation) records
    the bump and runs on, to measure contact."""
    options = {} if end_on_bump else {"family_options": {"end_on_bump": False}}
    return make_env(cfg, camera=camera, family="chae", reward="chae", step_s=STEP_S, **options)


# ----------------------------------------------------------------------------- training
def episode_scenario(seed: int, episode: int, ttc_range=TTC_RANGE) -> tuple[ChaeSpec, int]:
    """Training episode ``episode``'s scenario and observation-noise seed: a function of (seed, episode) and the
    TTC range (``agent.chae_ttc_range``) only, so a resumed run draws what an uninterrupted one would."""
    rng = np.random.default_rng([int(seed), CHAE_TRAINING_EPISODES, int(episode)])
    return sample_chae(rng, ttc_range=(float(ttc_range[0]), float(ttc_range[1]))), int(rng.integers(2**31))


def train(cfg, run_, agent_id: AgentId) -> dict:
    """``train_agent`` for ``agent.learner=dqn``: ``agent.episodes`` episodes of family chae."""
    from tqdm import tqdm

    from ..models.dqn import DQN

    if agent_id.reward != "chae":
        raise StageError(
            f"agent.learner=dqn learns Chae's braking with reward chae, not {agent_id.reward}: use agent=dqn_chae"
        )
    episodes = int(cfg.agent.episodes)
    sel = cfg.agent.select
    for key in ("seed", "rescore_seed") if sel.rescore else ("seed",):
        if sel.every and int(sel[key]) == int(cfg.evaluate.chae.seed):
            raise StageError(
                f"agent.select.{key}={sel[key]} is the evaluation's draw (evaluate.chae.seed): checkpoints must be "
                f"chosen on other trials; give agent.select.{key} another value"
            )
    see = observer(cfg, str(cfg.agent.obs))
    see_noise = see.view.noise_m if isinstance(see, HistoryObserver) else None  # what load_policy rebuilds
    env = family_env(cfg, see.camera)
    hp = dqn_config(cfg)
    agent = DQN(see.dim, len(BRAKE_LEVELS), hp, int(cfg.seed))
    episode, curve = resume_dqn(run_, agent, see.dim, {"return": [], "end": []})
    curve.setdefault("validation", [])
    first_validation = int(np.ceil(float(sel.start) * episodes))
    validation = Validation(sel, family_env(cfg, see.camera)) if sel.every else None

    def snapshot(best: bool = False, keep: bool = False):
        state = dqn_checkpoint(
            agent, hp, episode, curve, str(cfg.agent.obs), see.dim, agent_id.reward, noise_m=see_noise
        )
        if keep:
            atomic_torch_save(state, validated_path(run_.dir, episode))
        run_.save(state, best=best)

    writer = run_.writer
    recent: deque = deque(maxlen=ROLLING)
    recent.extend(e == "bump" for e in curve["end"][-ROLLING:])
    loss = None

    def play_episode():
        """One training episode, logged; a validation (or a checkpoint) when it falls due."""
        nonlocal episode, loss
        spec, view_seed = episode_scenario(int(cfg.seed), episode, cfg.agent.chae_ttc_range)
        obs, _ = env.reset(options={"scenario": spec})
        see.reset(view_seed)
        x, ret = see(env, obs), 0.0
        while True:
            a = agent.act(x)
            action = brake_action(a)
            obs, reward, terminated, truncated, info = env.step(action)
            see.note_action(action)
            x_next = see(env, obs)
            bump = terminated and info["outcome"]["end"] == "bump"
            agent.remember(x, a, reward, x_next, terminated, trauma=bump, episode_end=terminated or truncated)
            stats = agent.update()
            loss = stats["loss"] if stats else loss
            x, ret = x_next, ret + reward
            if terminated or truncated:
                break
        end = info["outcome"]["end"]
        curve["return"].append(float(ret))
        curve["end"].append(end)
        recent.append(end == "bump")
        episode += 1
        writer.add_scalar("episode/return", ret, episode)
        writer.add_scalar("episode/bump_rate_rolling", float(np.mean(recent)), episode)
        writer.add_scalar("train/epsilon", agent.epsilon(), episode)
        if loss is not None:
            writer.add_scalar("train/loss", loss, episode)
        if validation is not None and episode >= first_validation and episode % int(sel.every) == 0:
            score = validation.score(DQNPolicy("validation", agent, see, int(cfg.seed)), episode)
            improved = selected(curve["validation"] + [score], float(sel.max_bump)) is score
            curve["validation"].append(score)
            writer.add_scalar("validation/max_bump_rate", score["max_bump_rate"], episode)
            writer.add_scalar("validation/unnecessary_stop_rate", score["unnecessary_stop_rate"], episode)
            snapshot(best=improved, keep=bool(sel.keep))
        elif episode % CHECKPOINT_EPISODES == 0:
            snapshot()

    # episode -> its rescoring, per rescoring draw: a checkpoint is scored once, by a resumed run too
    draw = f"seed {sel.rescore_seed}, {sel.rescore_trials} trials, TTCs {list(sel.rescore_ttcs or [sel.ttcs[0]])}"
    rescore_cache: dict = curve.setdefault("rescorings", {}).setdefault(draw, {})

    def choose() -> tuple[dict | None, dict | None]:
        """The validation score best.pt holds and, with rescoring, the rescoring (best.pt then its choice)."""
        chosen, rescored = selected(curve["validation"], float(sel.max_bump)), None
        if validation is not None and sel.rescore:
            rescored = rescore_kept(cfg, agent_id, run_.dir, curve["validation"], cache=rescore_cache)
            if rescored["chosen"] is not None:
                episode_chosen = rescored["chosen"]["episode"]
                atomic_write_bytes(run_.best, validated_path(run_.dir, episode_chosen).read_bytes())
                chosen = next(s for s in curve["validation"] if s["episode"] == episode_chosen)
        return chosen, rescored

    # training on needs the rescoring's verdict: without validation (agent.select.every=0) there is none
    block, blocks = (int(sel.extend), int(sel.extend_blocks)) if validation is not None and sel.rescore else (0, 0)
    # the planned episodes, then whole blocks until the rescoring finds a member inside both bars
    target = first_target(episode, episodes, block)
    gates = curve.setdefault("gates", [])  # each rescoring's verdict: did it find a member inside both bars?
    run_.restore_random_state()  # building the networks and views drew from them
    with tqdm(total=target, initial=episode, desc=f"dqn chae ({cfg.agent.obs})", unit="episode") as bar:
        while True:
            while episode < target and not run_.stop.requested:
                play_episode()
                bar.update(1)
            if run_.stop.requested:
                snapshot()
                break
            chosen, rescored = choose()
            verdict = {"episode": episode, "member": member_found(rescored, sel)}
            if gates and gates[-1]["episode"] == episode:  # a finished run resumed: the same verdict again
                gates.pop()
            gates.append(verdict)
            snapshot()  # with the rescoring and its verdict in the curve: a resumed run need not drive it again
            if not block or target >= episodes + blocks * block or gates[-1]["member"]:
                break
            log.info("[%s] no rescored member inside both bars at episode %d: %d more", run_.name, episode, block)
            target += block
            bar.total = target
            bar.refresh()
    env.close()
    if validation is not None:
        validation.env.close()
    if run_.stop.requested:
        return run_.stopped(agent.steps)
    last = curve["end"][-ROLLING:]
    return {
        "reward": agent_id.reward,
        "obs": str(cfg.agent.obs),
        "episodes": episode,
        "steps": agent.steps,
        "recent_bump_rate": float(np.mean([e == "bump" for e in last])) if last else None,
        "recent_stop_rate": float(np.mean([e == "stop" for e in last])) if last else None,
        "selected": chosen,
        "rescored": rescored,
        "extended": max(0, episode - episodes),
        "gates": gates,
        "curve": curve,
    }


def first_target(episode: int, episodes: int, block: int) -> int:
    """The episode a run at ``episode`` trains to before its next rescoring: the planned ``episodes``, or, for a run
    resumed inside an extension block of ``block`` episodes, that block's end."""
    if not block or episode <= episodes:
        return episodes
    return episodes + -(-(episode - episodes) // block) * block


# ----------------------------------------------------------------------------- checkpoint selection
def validated_path(run_dir, episode: int):
    """Where ``agent.select.keep`` keeps the checkpoint validated after ``episode`` episodes."""
    return run_dir / "validated" / f"episode{int(episode):05d}.pt"


class Validation:
    """``agent.select``'s validation draw (``bank`` on its own seed), driven greedily by a checkpoint."""

    def __init__(self, sel, env):
        self.ttcs = [float(t) for t in sel.ttcs]
        self.entries = bank(SimpleNamespace(seed=int(sel.seed), trials=int(sel.trials), ttcs=self.ttcs))
        self.env = env

    def score(self, policy, episode: int) -> dict:
        """Bump rate per TTC (%), the worst of them, and Scenario 2's unnecessary stops (%)."""
        rows = run_policy(self.env, policy, self.entries, leave=False)
        s = summarise(rows, self.ttcs)["policies"][policy.name]
        bumps = {str(t): rate for t, rate in s["bump_rate"].items()}
        return {
            "episode": int(episode),
            "bump_rate": bumps,
            "max_bump_rate": max(bumps.values()),
            "unnecessary_stop_rate": s["unnecessary_stop_rate"],
        }


def selected(scores: list[dict], max_bump: float) -> dict | None:
    """The validation score ``best.pt`` holds: among the checkpoints bumping in at most ``max_bump`` % at every
    TTC, the one with the fewest unnecessary stops; if none, the one bumping least (fewer stops breaking ties).
    The earliest wins a tie, so a later checkpoint replaces it only by doing strictly better."""

    def key(s):
        safe = s["max_bump_rate"] <= max_bump
        return (0, s["unnecessary_stop_rate"]) if safe else (1, s["max_bump_rate"], s["unnecessary_stop_rate"])

    return min(scores, key=key) if scores else None


def rescore_shortlist(scores: list[dict], k: int, max_bump: float, max_stops: float, ttc: float) -> list[dict]:
    """Training's validation scores inside both bars (bumps <= ``max_bump`` % at every TTC, needless stops <=
    ``max_stops`` %), the ``k`` bumping least at ``ttc`` (then fewer stops, then later checkpoints first)."""
    inside = [s for s in scores if s["max_bump_rate"] <= max_bump and s["unnecessary_stop_rate"] <= max_stops]
    return sorted(inside, key=lambda s: (s["bump_rate"][str(ttc)], s["unnecessary_stop_rate"], -s["episode"]))[:k]


def room(score: dict, max_bump: float, max_stops: float) -> float:
    """How close a checkpoint comes to the bars: max(bumps / max_bump, stops / max_stops); below 1 is inside both."""
    return max(score["bump_rate"] / max_bump, score["unnecessary_stop_rate"] / max_stops)


def rescore_choice(rescored: list[dict], max_bump: float, max_stops: float) -> dict | None:
    """The rescored checkpoint with the most room under the bars, the later on a tie."""
    key = lambda s: (room(s, max_bump, max_stops), -s["episode"])  # noqa: E731
    return min(rescored, key=key) if rescored else None


def member_found(rescored: dict | None, sel) -> bool:
    """Whether the rescoring chose a checkpoint inside both bars on its draw (``agent.select.extend`` stops)."""
    chosen = (rescored or {}).get("chosen")
    return chosen is not None and room(chosen, float(sel.max_bump), float(sel.max_stops)) <= 1.0


def rescore_kept(cfg, agent_id: AgentId, run_dir, scores: list[dict], sel=None, cache: dict | None = None) -> dict:
    """``agent.select.rescore``: the shortlisted kept checkpoints of the run in ``run_dir`` on the rescoring draw
    (``sel``: the run's select settings, default ``cfg.agent.select``) at ``sel.rescore_ttcs`` (None: ``ttcs[0]``).
    Returns the draw, every shortlisted checkpoint's bumps per TTC, their highest and the needless stops, and the
    chosen one (None: no candidate). ``cache`` (str(episode) -> entry) holds checkpoints already rescored on this
    draw, and takes the new ones."""
    import torch

    sel = sel or cfg.agent.select
    corner, max_bump, max_stops = float(sel.ttcs[0]), float(sel.max_bump), float(sel.max_stops)
    ttcs = [float(t) for t in (getattr(sel, "rescore_ttcs", None) or [corner])]
    entries = bank(SimpleNamespace(seed=int(sel.rescore_seed), trials=int(sel.rescore_trials), ttcs=ttcs))
    env, rescored = None, []
    cache = {} if cache is None else cache
    for score in rescore_shortlist(scores, int(sel.rescore), max_bump, max_stops, corner):
        if str(score["episode"]) in cache:
            rescored.append(cache[str(score["episode"])])
            continue
        path = validated_path(run_dir, score["episode"])
        if not path.exists():
            raise StageError(f"{path} is missing: rescoring reads the checkpoints agent.select.keep=true keeps")
        policy = policy_from_state(cfg, agent_id, torch.load(path, map_location="cpu", weights_only=False))
        env = env or family_env(cfg, camera=policy.see.camera, end_on_bump=False)
        s = summarise(run_policy(env, policy, entries, leave=False), ttcs)["policies"][policy.name]
        cache[str(score["episode"])] = {
            "episode": score["episode"],
            "bump_rate": max(s["bump_rate"].values()),  # the highest over the TTCs: what room() weighs
            "bump_rates": {str(t): s["bump_rate"][t] for t in ttcs},
            "unnecessary_stop_rate": s["unnecessary_stop_rate"],
        }
        rescored.append(cache[str(score["episode"])])
    if env is not None:
        env.close()
    chosen = rescore_choice(rescored, max_bump, max_stops)
    return {
        "seed": int(sel.rescore_seed),
        "trials": int(sel.rescore_trials),
        "ttc": corner,
        "ttcs": ttcs,
        "rescored": rescored,
        "chosen": chosen,
    }


def summary(metrics: dict) -> str:
    """One log line for a finished training run."""
    line = f"{metrics['episodes']} episodes; bumps in the last 100: {metrics['recent_bump_rate']}"
    chosen = metrics.get("selected")
    if chosen:
        line += (
            f"; best.pt = episode {chosen['episode']} (validation: bumps <= {chosen['max_bump_rate']:.1f} % per TTC, "
            f"{chosen['unnecessary_stop_rate']:.1f} % unnecessary stops)"
        )
    return line


# ----------------------------------------------------------------------------- policies
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
    """A trained dqn agent, built with the hyperparameters it was trained with: the checkpoint ``agent.select``
    chose on its validation draw (``best.pt``) when the run validated, else the last one."""
    state = artifacts.load_agent_state(cfg, agent_id, "last")
    # last.pt says whether the run validated (a best.pt alone could be left from another run's settings); a chae
    # checkpoint is small, so reading best.pt after it costs little
    if state.get("curve", {}).get("validation"):
        state = artifacts.load_agent_state(cfg, agent_id, "best")
        log.info("[eval chae] %s: best.pt, episode %d, chosen on the validation draw", agent_id.key, state["episode"])
    return policy_from_state(cfg, agent_id, state)


def policy_from_state(cfg, agent_id: AgentId, state: dict) -> DQNPolicy:
    """The greedy policy of one dqn checkpoint of run ``agent_id`` (``last.pt``, ``best.pt`` or a kept one)."""
    from omegaconf import OmegaConf

    from ..config import agent_preset
    from ..models.dqn import DQN, DQNConfig

    if state.get("learner") != "dqn":
        raise StageError(
            f"{agent_id.dir(cfg)} is not a dqn agent; delete it or move it out of {artifacts.runs_root(cfg)}"
        )
    # checkpoints from before agent.chae_noise_m were all trained at the default 0.1 m
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
    agent = DQN(see.dim, len(BRAKE_LEVELS), hp, agent_id.seed)
    agent.load_state_dict(state["agent"])
    return DQNPolicy(agent_id.policy, agent, see, agent_id.seed)


# ----------------------------------------------------------------------------- evaluation
def bank(c) -> list[tuple[int, ChaeSpec]]:
    """(scenario, spec): Scenario 1 at every TTC of ``c.ttcs`` and Scenario 2, ``c.trials`` each, seeded."""
    out = []
    for ttc in c.ttcs:
        rng = np.random.default_rng([int(c.seed), int(round(float(ttc) * 100))])
        for i in range(int(c.trials)):
            spec = ChaeSpec(
                seed=i,
                ttc=float(ttc),
                v_init=float(rng.uniform(*V_INIT_RANGE)),
                v_ped=float(rng.uniform(*V_PED_RANGE)),
                far_side=bool(rng.random() < 0.5),
            )
            out.append((1, spec))
    rng = np.random.default_rng([int(c.seed), CHAE_BANK_SCENARIO_2])
    for i in range(int(c.trials)):
        spec = ChaeSpec(
            seed=i,
            ttc=float(rng.uniform(1.5, 4.0)),
            v_init=float(rng.uniform(*V_INIT_RANGE)),
            v_ped=float(rng.uniform(*V_PED_RANGE)),
            far_side=bool(rng.random() < 0.5),
            crosses=False,
        )
        out.append((2, spec))
    return out


COLUMNS = (
    "policy",
    "policy_seed",
    "scenario",
    "ttc",
    "v_init",
    "v_ped",
    "far_side",
    "end",
    "bump",
    "contact",
    "impact_speed",
    "pedestrian_injury",
    "stop_gap",
)


def run_policy(env, policy, entries, policy_seed: int = 0, leave: bool = True) -> list[dict]:
    from tqdm import tqdm

    from envs.rollout import rollout

    rows = []
    for scenario, spec in tqdm(entries, desc=policy.name, unit="trial", leave=leave):
        o = rollout(env, policy, spec).outcome
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": policy_seed,
                "scenario": scenario,
                "ttc": spec.ttc,
                "v_init": spec.v_init,
                "v_ped": spec.v_ped,
                "far_side": int(spec.far_side),
                "end": o["end"],
                "bump": o["bumped"],
                "contact": int(o["pedestrian_collision"]),
                "impact_speed": o["speed_at_collision"] if o["pedestrian_collision"] else float("nan"),
                "pedestrian_injury": o["pedestrian_injury"],
                "stop_gap": o["gap_to_pedestrian"] if o["end"] == "stop" else float("nan"),
            }
        )
    return rows


def evaluate(cfg) -> dict:
    """``evaluate.family=chae``: every scripted policy and dqn agent on the same seeded trials."""
    from ..training import tensorboard

    c = drawn(cfg, "chae")
    out = artifacts.eval_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    entries = bank(c)
    agents = artifacts.trained_agents(cfg, family="chae")
    record = artifacts.provenance(cfg, "eval")
    learned = [load_policy(cfg, a) for a in agents]  # fail fast, before any trial runs
    if int(c.ensemble):
        grouped = ensembles(agents, learned, int(c.ensemble))
        learned = learned + grouped if c.singles else grouped
    rows = []
    plain = family_env(cfg, camera=False, end_on_bump=False)
    for name in c.policies:
        rows += run_policy(plain, SCRIPTED[name](), entries)
    plain.close()
    for policy in learned:
        env = family_env(cfg, camera=policy.see.camera, end_on_bump=False)
        rows += run_policy(env, policy, entries, policy.policy_seed)
        env.close()
    if not agents:
        log.info(
            "[eval chae] no dqn agents under %s: scripted policies only. Train one with "
            "`python -m worldmodel.train_agent experiment=%s agent=dqn_chae`.",
            artifacts.runs_root(cfg),
            cfg.experiment,
        )
    write_rows(out, rows, COLUMNS)
    summary = summarise(rows, [float(t) for t in c.ttcs])
    summary["render"] = {"trials": int(c.trials), "ttcs": [float(t) for t in c.ttcs]}  # what tables() is given
    (out / "tables.md").write_text(tables(summary, int(c.trials)))
    figures(rows, summary, out)
    learning_curves(cfg, agents, out / "learning_curves.png")
    writer = tensorboard(out)
    for policy, s in summary["policies"].items():
        for ttc, rate in s["bump_rate"].items():
            writer.add_scalar(f"chae/{policy}/bump_rate", rate, int(round(float(ttc) * 10)))
    writer.close()
    headline = {
        f"{r['policy']}/seed{r['seed']}": f"max bump {r['max_bump']:.2f} % (TTC {r['at_ttc']:g} s), needless stops "
        + ("n/a" if r["stops"] is None else f"{r['stops']:.2f} %")
        for r in summary["runs"]
    }
    record_if_test(cfg, "chae", rows, record, headline)
    seal(out, summary, record, t0)
    log.info(
        "[eval chae] %d trials x %d policies in %.0f s: %s",
        len(entries),
        len(c.policies) + len(learned),
        summary["wall_s"],
        out / "tables.md",
    )
    return summary


def render_tables(rows: list[dict], settings: dict) -> str:
    """The evaluation's tables from its rows and ``summary["render"]``."""
    return tables(summarise(rows, [float(t) for t in settings["ttcs"]]), int(settings["trials"]))


def ncap_policies(cfg) -> list[tuple]:
    """TTC braking, latest-safe braking and every dqn agent on the NCAP bank: pedestrian tests only, but the
    camera variant, which sees cars too."""
    out = [(TTCBraking(), 0, False, False), (LatestSafeBraking(), 0, False, False)]
    for agent in artifacts.trained_agents(cfg, family=FAMILY):
        policy = load_policy(cfg, agent)
        out.append((policy, agent.seed, policy.see.camera, policy.see.camera))
    return out


def _mean(values) -> float | None:
    values = [v for v in values if v == v]
    return float(np.mean(values)) if values else None


def summarise(rows: list[dict], ttcs: list[float]) -> dict:
    """Per policy (seeds pooled): bump, contact, impact speed and injury per TTC, and Scenario 2's stops."""
    out = {"ttcs": ttcs, "policies": {}}
    for policy in dict.fromkeys(r["policy"] for r in rows):
        mine = [r for r in rows if r["policy"] == policy]
        s1 = [r for r in mine if r["scenario"] == 1]
        s2 = [r for r in mine if r["scenario"] == 2]
        s: dict = {"seeds": sorted({r["policy_seed"] for r in mine}), "bump_rate": {}, "contact_rate": {}}
        s["impact_kmh"], s["injury"] = {}, {}
        for ttc in ttcs:
            at = [r for r in s1 if abs(r["ttc"] - ttc) < 1e-9]
            s["bump_rate"][ttc] = 100 * float(np.mean([r["bump"] for r in at]))
            s["contact_rate"][ttc] = 100 * float(np.mean([r["contact"] for r in at]))
            impact = _mean(r["impact_speed"] for r in at)
            s["impact_kmh"][ttc] = None if impact is None else 3.6 * impact
            s["injury"][ttc] = 100 * float(np.mean([r["pedestrian_injury"] for r in at]))
        s["unnecessary_stop_rate"] = 100 * float(np.mean([r["end"] == "stop" for r in s2])) if s2 else None
        s["stop_gaps"] = [r["stop_gap"] for r in s1 if r["stop_gap"] == r["stop_gap"]]
        out["policies"][policy] = s
    out["runs"] = bars_per_run(rows, ttcs)
    return out


def bars_per_run(rows: list[dict], ttcs: list[float]) -> list[dict]:
    """Each (policy, seed) against the bars: its highest bump rate at a TTC from ``BAR_FROM_TTC`` (and where),
    Scenario 2's needless stops, and whether it is inside both. Empty when no TTC reaches ``BAR_FROM_TTC``."""
    late = [t for t in ttcs if t >= BAR_FROM_TTC - 1e-9]
    out = []
    for policy, seed in dict.fromkeys((r["policy"], r["policy_seed"]) for r in rows) if late else ():
        mine = [r for r in rows if r["policy"] == policy and r["policy_seed"] == seed]
        bumps = {
            t: 100 * float(np.mean([r["bump"] for r in mine if r["scenario"] == 1 and abs(r["ttc"] - t) < 1e-9]))
            for t in late
        }
        worst = max(late, key=lambda t: (bumps[t], -t))  # the earliest of equal rates
        s2 = [r["end"] == "stop" for r in mine if r["scenario"] == 2]
        stops = 100 * float(np.mean(s2)) if s2 else None
        inside = bumps[worst] <= BAR_BUMP and stops is not None and stops <= BAR_STOPS
        out.append(
            {
                "policy": policy,
                "seed": int(seed),
                "max_bump": bumps[worst],
                "at_ttc": worst,
                "stops": stops,
                "inside": bool(inside),
            }
        )
    return out


def tables(summary: dict, trials: int) -> str:
    ttcs = summary["ttcs"]
    head = "| policy | " + " | ".join(f"{t:g}" for t in ttcs) + " |"
    rule = "|---|" + "---:|" * len(ttcs)

    def line(name, values, fmt="{:.1f}"):
        return f"| {name} | " + " | ".join("–" if v is None else fmt.format(v) for v in values) + " |"

    pol = summary["policies"]
    lines = [
        f"# Chae et al. on family chae ({trials} seeded trials per TTC and in Scenario 2; seeds pooled)",
        "",
        "## Table I layout: Scenario 1 bump rate, % (the bumper past the 3 m safety line while the pedestrian crosses)",
        "",
        head,
        rule,
        line("Chae et al. (paper, 10,000 trials)", [PAPER_TABLE_I.get(t, 0.0) for t in ttcs], "{:.2f}"),
        "| physics band (full braking at the trigger .. 0.1 s later) | "
        + " | ".join(f"{PHYSICS_BAND[t][0]:g}–{PHYSICS_BAND[t][1]:g}" if t in PHYSICS_BAND else "0" for t in ttcs)
        + " |",
    ]
    lines += [line(p, [s["bump_rate"][t] for t in ttcs]) for p, s in pol.items()]
    lines += [
        "",
        "## Scenario 2 (the pedestrian stays): unnecessary stops, %",
        "",
        "| policy | stops % |",
        "|---|---:|",
    ]
    lines += [f"| {p} | {s['unnecessary_stop_rate']:.1f} |" for p, s in pol.items()]
    for key, title in (
        ("contact_rate", "footprint contact with the pedestrian, %"),
        ("impact_kmh", "mean impact speed of the contacts, km/h"),
        ("injury", "mean Rosén pedestrian severe-injury risk per trial, %"),
    ):
        lines += ["", f"## Scenario 1: {title}", "", head, rule]
        lines += [line(p, [s[key][t] for t in ttcs]) for p, s in pol.items()]
    if summary.get("runs"):
        lines += [
            "",
            f"## The bars, run by run: bumps <= {BAR_BUMP:g} % at every TTC from {BAR_FROM_TTC:g} s, needless stops "
            f"<= {BAR_STOPS:g} %",
            "",
            f"| policy | seed | highest bump rate from {BAR_FROM_TTC:g} s, % (at TTC, s) | needless stops % | inside |",
            "|---|---:|---:|---:|---|",
        ]
        for r in summary["runs"]:
            stops = "–" if r["stops"] is None else f"{r['stops']:.1f}"
            verdict = "yes" if r["inside"] else "no"
            lines.append(
                f"| {r['policy']} | {r['seed']} | {r['max_bump']:.1f} ({r['at_ttc']:g}) | {stops} | {verdict} |"
            )
    lines += [
        "",
        "Stopping distance (Fig. 7 layout): `stopping_distance.png`, the gap from the front bumper to the "
        "pedestrian's line when the car stood still in Scenario 1.",
    ]
    return "\n".join(lines) + "\n"


def figures(rows: list[dict], summary: dict, out) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ttcs = summary["ttcs"]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(ttcs, [PAPER_TABLE_I.get(t, 0.0) for t in ttcs], "k--", label="Chae et al. (paper)")
    for p, s in summary["policies"].items():
        ax.plot(ttcs, [s["bump_rate"][t] for t in ttcs], marker="o", ms=3, label=p)
    _finish(fig, ax, "TTC at the pedestrian's start, s", "bump rate, %", out / "bump_rate.png")

    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.arange(0.0, 30.5, 1.0)
    for p, s in summary["policies"].items():
        if s["stop_gaps"]:
            ax.hist(s["stop_gaps"], bins=bins, histtype="step", label=f"{p} ({len(s['stop_gaps'])} stops)")
    ax.axvline(SAFETY_LINE_M, color="r", ls=":", label="safety line (3 m)")
    _finish(
        fig,
        ax,
        "gap from the bumper to the pedestrian's line at standstill, m",
        "Scenario-1 trials",
        out / "stopping_distance.png",
    )


def _finish(fig, ax, xlabel: str, ylabel: str, path) -> None:
    import matplotlib.pyplot as plt

    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def learning_curves(cfg, agents: list[AgentId], path) -> None:
    """Each finished agent's training curve (rolling 100 episodes): bump rate and return, the paper's Fig. 5
    comparison when agents with and without the trauma memory are both there."""
    curves = {}
    for agent in agents:
        metrics = agent.dir(cfg) / "metrics.json"
        if metrics.exists():
            curves[agent.key] = json.loads(metrics.read_text()).get("curve")
    curves = {k: v for k, v in curves.items() if v}
    if not curves:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def rolling(x):
        x = np.asarray(x, float)
        return np.convolve(x, np.ones(ROLLING) / ROLLING, mode="valid") if len(x) >= ROLLING else x

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for key, curve in curves.items():
        axes[0].plot(100 * rolling([e == "bump" for e in curve["end"]]), label=key, lw=1)
        axes[1].plot(rolling(curve["return"]), label=key, lw=1)
    axes[0].set_title(f"bumps, % of the last {ROLLING} training episodes")
    axes[1].set_title(f"return (Eq. 8), rolling {ROLLING} episodes")
    for ax in axes:
        ax.set_xlabel("episode")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
