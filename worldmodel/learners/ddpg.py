"""The paper's learner (``agent.learner=ddpg``): DDPG acting from [z_t, zhat_{t+1}] in the live simulator, with reward
R1 or R2, or from the true state (``obs=privileged``); with the planner's demonstrations, cloning and DAgger rounds
where the preset asks. ``python -m worldmodel.train_agent`` runs it (docs/design.md §5).

Episodes are the paper's scenarios (section IV-A, including ones with no hazard, where the policy must do no
harm), truncated ``env.horizon_after_ttc_s`` after the TTC. The reward is 0 except on the step of a collision
(R1 = -people involved, R2 = -sum of injury probabilities), exactly as in the paper.

Writes ``runs/NAME/agent_r1/seed0/`` (reward, then training seed): ``last.pt`` (actor, critic, targets,
optimisers, replay buffer, step, RNG, provenance) every ``agent.checkpoint_every`` steps, ``best.pt`` (best
rolling return), TensorBoard (episodic return, collision rate by kind, injury sums, losses, Q, steps/s) and
``metrics.json`` when finished. A checkpoint taken inside an episode keeps that episode's start and actions, its
n-step window and the latest losses, so a resumed run replays the episode to the saved step and goes on exactly as
an uninterrupted run would: the same replay buffer, weights, optimiser and random states, episode count and
TensorBoard steps.
"""

from __future__ import annotations

import logging
import time
from collections import deque

import numpy as np

from envs.streams import AGENT_EPISODE_SEEDS, AGENT_FOCUS_EPISODES

from .. import loading, registry
from ..action_map import ActionMap
from ..common import StageError, make_env, resolve_device, seed_everything
from ..config import validate
from ..imitation import cloning_fit, dagger_labels, demonstration_buffer, mixed_batch
from ..models.ddpg import DDPGConfig, NStepWindow, ReplayBuffer
from ..models.td3 import make_agent
from ..training import EpisodeInProgress, TrainingRun
from .cloning import clone
from .loop import Callbacks, TrainingLoop

log = logging.getLogger(__name__)
ROLLING = 100
OUTCOME_KEYS = (
    "pedestrian_collision",
    "vehicle_collision",
    "static_collision",
    "pedestrian_injury",
    "occupant_injury",
    "lane_departure",
)


def episode_seed(seed: int, episode: int) -> int:
    return int(np.random.default_rng([seed, AGENT_EPISODE_SEEDS, episode]).integers(0, 2**31 - 1))


def reset_options(cfg, episode: int) -> dict:
    """How training episode ``episode`` starts: a focus-mix scenario with probability ``agent.focus_share``,
    else the paper's distributions from the episode's seed. Depends only on (seed, episode). ``cfg``: the typed
    config (``validate``), or the composed one, whose values have the same types."""
    seed, share = cfg.seed, cfg.agent.focus_share
    if share > 0:
        from envs import sample_focus_scenario

        rng = np.random.default_rng([seed, AGENT_FOCUS_EPISODES, episode])
        if rng.uniform() < share:
            f = cfg.demos.focus
            spec = sample_focus_scenario(rng, f.hazard_share, tuple(f.speed_range), tuple(f.ttc_range))
            return {"options": {"scenario": spec}}
    return {"seed": episode_seed(seed, episode)}


def run(cfg, agent_id) -> dict:
    """Train the agent ``agent_id`` (the paper's street scenarios for ``obs=privileged``)."""
    typed = validate(cfg)
    if typed.agent.obs == "privileged":  # the true state (envs/privileged.py): no world model, no camera
        paper = registry.default()
        if registry.of_reward(agent_id.reward) is not paper or typed.env.family != paper.name:
            raise StageError(
                f"obs=privileged trains on the paper's street scenarios: env.family={paper.name}, reward="
                + " or ".join(paper.rewards)
            )
    return DDPGRun(cfg, typed, agent_id).train()


def build_policy(name: str, encoder, state: dict, device="cpu"):
    """A trained agent's actor as a policy, acting through ``encoder`` with the action map it was trained with."""
    from ..agent_obs import LearnedPolicy
    from ..models.ddpg import Actor

    actor = Actor(state["obs_dim"], 2, tuple(state["actor_hidden"]))
    actor.load_state_dict(state["agent"]["actor"])
    return LearnedPolicy(
        name, encoder, actor.eval().to(device), action_map=ActionMap.from_dict(state.get("action_map"))
    )


class DDPGLearner:
    """DDPG or TD3 (``models.td3.make_agent``) as a ``Learner`` of the training loop (learners/loop.py): uniform
    random actions for ``warmup_steps``, then the actor with Gaussian noise; each step's transition through the
    n-step window into the replay memory, its reward times ``reward_scale``; once warmed up, one minibatch per step,
    with the planner's demonstrations mixed in where ``demos`` holds them (``demo_share`` of each batch).

    The n-step window holds only transitions of the episode in progress: a run that saves inside episodes keeps it
    with that episode."""

    def __init__(self, agent, reward_scale: float = 1.0, demo_share: float = 0.0, demos=None):
        """``agent``: a DDPG or TD3, whose config (``agent.cfg``, DDPG's keys alone) sets the warm-up, the batch,
        the replay's size and the n-step returns; rewards go into the replay times ``reward_scale``, and
        ``demo_share`` of every batch comes from ``demos`` where it holds demonstrations."""
        self.agent, self.reward_scale, self.demo_share, self.demos = agent, reward_scale, demo_share, demos
        hp = agent.cfg
        self.buffer = ReplayBuffer(hp.buffer_size, agent.obs_dim, agent.act_dim)
        self.window = NStepWindow(hp.n_step, hp.gamma)
        self.steps = 0

    def act(self, obs, explore: bool) -> np.ndarray:
        if explore and self.steps < self.agent.cfg.warmup_steps:
            return self.agent.random_action()
        return self.agent.act(obs, explore=explore)

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool, info: dict) -> None:
        self.window.store(self.buffer, obs, action, reward * self.reward_scale, next_obs, terminated, truncated)
        self.steps += 1

    def update(self) -> dict | None:
        agent = self.agent
        hp = agent.cfg
        if self.steps <= hp.warmup_steps or len(self.buffer) < hp.batch_size:
            return None
        return agent.update(mixed_batch(self.buffer, self.demos, hp.batch_size, self.demo_share, agent.rng))

    def state_dict(self) -> dict:
        return {"agent": self.agent.state_dict(), "buffer": self.buffer.state_dict(), "step": self.steps}

    def load_state_dict(self, state) -> None:
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.steps = int(state["step"])


class WorldModelEpisodes:
    """The paper's training episodes (``reset_options``) through the world model's view, each kept as it goes
    (``EpisodeInProgress``) so that a checkpoint inside it resumes exactly."""

    def __init__(self, view, typed):
        self.current, self.typed = EpisodeInProgress(view), typed

    def start(self, episode: int):
        return self.current.reset(**reset_options(self.typed, episode))[0]

    def step(self, action) -> tuple:
        return self.current.step(action)


class DDPGRun(Callbacks):
    """The paper's DDPG in the live simulator, acting from the world model's view of the camera (or, with
    ``obs=privileged``, from the true state), with its cloning rounds and demonstrations where the preset asks."""

    def __init__(self, cfg, typed, agent_id):
        """``typed``: ``cfg`` validated."""
        from ..agent_obs import WorldModelView

        self.cfg, self.typed, self.agent_id = cfg, typed, agent_id
        if typed.agent.obs == "privileged":
            from ..agent_obs import PrivilegedEncoder

            sim = make_env(cfg, camera=False)
            encoder = PrivilegedEncoder(sim)
        else:
            encoder = loading.load_world_model(cfg)
            sim = make_env(cfg)
        self.hp = hp = typed.agent
        self.encoder, self.action_map = encoder, ActionMap(hp.anchor, hp.steer, sim.params)
        self.env = WorldModelView(sim, encoder, self.action_map)
        seed_everything(typed.seed)
        self.obs_dim = encoder.dim
        agent = make_agent(self.obs_dim, 2, DDPGConfig.of(hp), seed=typed.seed, device=resolve_device(typed.device))
        self.learner = DDPGLearner(agent, hp.reward_scale, hp.demo_share)
        self.agent = self.learner.agent
        self.history: deque = deque(maxlen=ROLLING)
        self.demo_info, self.held_out = {}, None
        if hp.demo_share > 0 or hp.bc_pretrain_steps > 0:
            self.learner.demos, self.demo_info = demonstration_buffer(
                cfg, encoder, self.action_map, agent_id.reward, hp, "train"
            )
            self.held_out, _ = demonstration_buffer(cfg, encoder, self.action_map, agent_id.reward, hp, "validation")
            log.info(
                "[%s] %d demonstration transitions from %d planner episodes",
                agent_id.policy,
                len(self.learner.demos),
                self.demo_info["episodes"],
            )
        self.episodes = WorldModelEpisodes(self.env, typed)
        self.best_return = -float("inf")
        self.rounds = hp.dagger_rounds + 1 if hp.bc_pretrain_steps > 0 else 0  # cloning rounds before the first step
        self.cloned, self.cloning_set = 0, None

    def resume(self, run_) -> int:
        """Restore the learner and the run's counters from ``run_``'s checkpoint; returns its episode count."""
        state = run_.state
        if state["obs_dim"] != self.obs_dim:
            raise StageError(
                f"{run_.last} expects agent inputs of size {state['obs_dim']}, the world model "
                f"gives {self.obs_dim} (vae.latent_dim / agent.use_speed / agent.frame_view changed); delete "
                f"{run_.dir} to retrain"
            )
        self.learner.load_state_dict(state)
        self.best_return = state["best_return"]
        self.history.extend(state["history"])
        self.cloned, self.cloning_set = state.get("cloned_rounds", self.rounds), state.get("cloning_set")
        self.demo_info = state.get("demonstrations", self.demo_info)
        cloning = f", {self.cloned} of {self.rounds} cloning rounds" if self.rounds else ""
        run_.resumed(f"step {self.learner.steps}, episode {state['episode']}{cloning}")
        return state["episode"]

    def snapshot(self, best: bool = False) -> None:
        hp, loop = self.hp, self.loop
        self.run_.save(
            {
                **self.learner.state_dict(),
                "episode": loop.episode,
                "best_return": self.best_return,
                "history": list(self.history),
                "obs": hp.obs,
                "obs_dim": self.obs_dim,
                "actor_hidden": list(hp.ddpg.actor_hidden),
                "action_map": self.action_map.to_dict(),
                "use_speed": hp.use_speed,
                "frame_view": hp.frame_view,
                "reward": self.agent_id.reward,
                "demonstrations": self.demo_info,
                "cloned_rounds": self.cloned,
                # the examples the next cloning round fits, DAgger's labels among them; dropped once cloned
                "cloning_set": self.cloning_set if self.cloned < self.rounds else None,
                "in_progress": {
                    **self.episodes.current.state_dict(),
                    "return": loop.ret,
                    "window": self.learner.window.state_dict(),
                    "losses": dict(loop.losses),
                },
            },
            best=best,
        )

    def clone_rounds(self) -> None:
        """The cloning rounds still to do (each saved: a stop waits for the round to end, and resumes after it)."""
        run_, demos = self.run_, self.learner.demos
        if self.cloning_set is None:
            self.cloning_set = (demos.obs[: len(demos)], demos.actions[: len(demos)])
        resumed_at = self.cloned * self.hp.bc_pretrain_steps if run_.state is not None else None
        pretrain_writer = run_.side_writer("pretrain", purge_step=resumed_at)
        while self.cloned < self.rounds and not run_.stop.requested:
            self.cloning_set = cloning_round(
                self.cfg,
                self.hp,
                self.agent,
                self.encoder,
                self.action_map,
                self.cloning_set,
                self.held_out,
                self.cloned,
                run_,
                pretrain_writer,
                self.demo_info,
            )
            self.cloned += 1
            if self.cloned == self.rounds:
                self.agent.sync_targets()
            self.snapshot()

    def start(self) -> None:
        """The episode in progress: the checkpoint's, replayed to its step, or a new one."""
        run_, loop = self.run_, self.loop
        progress = run_.state.get("in_progress") if run_.state is not None else None
        if progress and len(progress["actions"]):
            obs, _ = self.episodes.current.resume(progress, run_.last)
            self.learner.window.load_state_dict(progress["window"])
            loop.losses = dict(progress["losses"])
            loop.begin(obs, progress["return"], len(progress["actions"]))
        else:
            loop.begin()

    def on_episode(self, loop, outcome: dict, ret: float, length: int) -> None:
        self.history.append({k: outcome[k] for k in OUTCOME_KEYS} | {"return": ret, "hazard": outcome["hazard"]})
        rolling = log_episode(self.run_.writer, self.history, outcome, ret, length, loop.step)
        # the next episode has started (a mid-episode loop): a checkpoint here holds no finished one
        warm = loop.step > self.hp.ddpg.warmup_steps
        if warm and len(self.history) >= min(ROLLING, 20) and rolling > self.best_return:
            self.best_return = rolling
            self.snapshot(best=True)

    def on_step(self, loop) -> None:
        step = loop.step
        if loop.losses and step % 50 == 0:
            for k, v in loop.losses.items():
                self.run_.writer.add_scalar(f"train/{k}", v, step)
            self.run_.writer.add_scalar("speed/steps_per_s", self.rate(), step)
        if step % self.hp.checkpoint_every == 0:
            self.snapshot()

    def rate(self) -> float:
        """Steps per second in this process."""
        return (self.loop.step - self.first_step) / (time.perf_counter() - self.t0)

    def train(self) -> dict:
        from tqdm import tqdm

        agent_id, hp = self.agent_id, self.hp
        with TrainingRun.for_agent(self.cfg, agent_id) as run_:
            self.run_ = run_
            episode = self.resume(run_) if run_.state is not None else 0
            self.loop = TrainingLoop(self.learner, self.episodes, run_, self, episode=episode, mid_episode=True)
            if self.cloned < self.rounds:
                self.clone_rounds()
            self.start()
            self.t0, self.first_step = time.perf_counter(), self.loop.step
            with tqdm(
                total=hp.total_steps, initial=self.loop.step, desc=f"agent {agent_id.reward}", unit="step"
            ) as bar:
                self.loop.run(lambda: self.loop.step >= hp.total_steps, bar)
            self.snapshot()
            self.env.close()
            if run_.stop.requested:
                return run_.stopped(self.loop.step)
            return run_.finish(self.metrics(round(self.rate(), 1)))

    def metrics(self, steps_per_s: float) -> dict:
        recent = list(self.history)
        metrics = {
            "reward": self.agent_id.reward,
            "steps": self.loop.step,
            "episodes": self.loop.episode,
            "rolling_return": float(np.mean([h["return"] for h in recent])) if recent else None,
            "best_rolling_return": self.best_return if self.best_return > -float("inf") else None,
            "recent_collision_rate": {
                k: float(np.mean([h[f"{k}_collision"] for h in recent])) if recent else None
                for k in ("pedestrian", "vehicle", "static")
            },
            "steps_per_s": steps_per_s,
            "demonstrations": self.demo_info,
        }
        log.info(
            "[%s] %d steps, %d episodes; rolling return %s; wrote %s",
            self.agent_id.policy,
            self.loop.step,
            self.loop.episode,
            metrics["rolling_return"],
            self.run_.dir,
        )
        return metrics


def cloning_round(
    cfg, hp, agent, encoder, action_map, cloning_set, held_out, round_: int, run_, writer, demo_info: dict
):
    """Cloning round ``round_`` (0: the planner's demonstrations; from 1, DAgger: its labels on the student's own
    states join them first) with the typed agent section ``hp``. Returns the examples the round fitted;
    ``demo_info`` gains the round's figures."""
    inputs, targets = cloning_set
    name = run_.name
    if round_:
        x, y, outcome = dagger_labels(cfg, agent, encoder, action_map, round_)
        inputs, targets = np.concatenate([inputs, x]), np.concatenate([targets, y])
        log.info(
            "[%s] DAgger round %d: %d planner labels on the student's states; its episodes: %s",
            name,
            round_,
            len(x),
            outcome,
        )
        demo_info[f"dagger_round{round_}"] = {"labels": len(x), "student": outcome}
    loss = clone(agent, inputs, targets, hp, writer, round_, held_out)
    demo_info[f"after_cloning_round{round_}"] = cloning_fit(agent, held_out)
    log.info(
        "[%s] cloned the planner (round %d, %d examples, %d minibatches): training loss %.4f; held-out %s",
        name,
        round_,
        len(inputs),
        hp.bc_pretrain_steps,
        loss,
        demo_info[f"after_cloning_round{round_}"],
    )
    return inputs, targets


def log_episode(writer, history, outcome: dict, ep_return: float, ep_len: int, step: int) -> float:
    """One finished episode to TensorBoard, with rolling rates over ``history``; returns the rolling return."""
    writer.add_scalar("episode/return", ep_return, step)
    writer.add_scalar("episode/length", ep_len, step)
    writer.add_scalar("episode/pedestrian_injury", outcome["pedestrian_injury"], step)
    writer.add_scalar("episode/occupant_injury", outcome["occupant_injury"], step)
    for kind in ("pedestrian", "vehicle", "static"):
        writer.add_scalar(f"collision_rate/{kind}", np.mean([h[f"{kind}_collision"] for h in history]), step)
    writer.add_scalar("episode/lane_departure_rate", np.mean([h["lane_departure"] for h in history]), step)
    rolling = float(np.mean([h["return"] for h in history]))
    writer.add_scalar("episode/return_rolling", rolling, step)
    return rolling
