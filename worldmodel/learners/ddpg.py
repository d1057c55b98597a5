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
from ..common import StageError, check_finite, make_env, resolve_device, seed_everything
from ..config import validate
from ..imitation import clone, cloning_fit, dagger_labels, demonstration_buffer, mixed_batch
from ..models.ddpg import DDPG, NStepWindow, ReplayBuffer, progress_state
from ..training import EpisodeInProgress, TrainingRun

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


class DDPGRun:
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
        self.agent = DDPG(self.obs_dim, 2, hp, seed=typed.seed, device=resolve_device(typed.device))
        self.buffer = ReplayBuffer(hp.buffer_size, self.obs_dim, 2)
        self.history: deque = deque(maxlen=ROLLING)
        self.demos, self.demo_info, self.held_out = None, {}, None
        if hp.demo_share > 0 or hp.bc_pretrain_steps > 0:
            self.demos, self.demo_info = demonstration_buffer(
                cfg, encoder, self.action_map, agent_id.reward, hp, "train"
            )
            self.held_out, _ = demonstration_buffer(cfg, encoder, self.action_map, agent_id.reward, hp, "validation")
            log.info(
                "[%s] %d demonstration transitions from %d planner episodes",
                agent_id.policy,
                len(self.demos),
                self.demo_info["episodes"],
            )
        self.window = NStepWindow(hp.n_step, hp.gamma)
        self.current = EpisodeInProgress(self.env)
        self.losses: dict = {}
        self.step, self.episode, self.best_return = 0, 0, -float("inf")
        self.rounds = hp.dagger_rounds + 1 if hp.bc_pretrain_steps > 0 else 0  # cloning rounds before the first step
        self.cloned, self.cloning_set, self.ep_return = 0, None, 0.0

    def resume(self, run_) -> None:
        state = run_.state
        if state["obs_dim"] != self.obs_dim:
            raise StageError(
                f"{run_.last} expects agent inputs of size {state['obs_dim']}, the world model "
                f"gives {self.obs_dim} (vae.latent_dim / agent.use_speed / agent.frame_view changed); delete "
                f"{run_.dir} to retrain"
            )
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.step, self.episode, self.best_return = state["step"], state["episode"], state["best_return"]
        self.history.extend(state["history"])
        self.cloned, self.cloning_set = state.get("cloned_rounds", self.rounds), state.get("cloning_set")
        self.demo_info = state.get("demonstrations", self.demo_info)
        cloning = f", {self.cloned} of {self.rounds} cloning rounds" if self.rounds else ""
        run_.resumed(f"step {self.step}, episode {self.episode}{cloning}")

    def snapshot(self, best: bool = False) -> None:
        hp = self.hp
        self.run_.save(
            {
                **progress_state(self.agent, self.buffer, self.step, self.episode),
                "best_return": self.best_return,
                "history": list(self.history),
                "obs": hp.obs,
                "obs_dim": self.obs_dim,
                "actor_hidden": list(hp.actor_hidden),
                "action_map": self.action_map.to_dict(),
                "use_speed": hp.use_speed,
                "frame_view": hp.frame_view,
                "reward": self.agent_id.reward,
                "demonstrations": self.demo_info,
                "cloned_rounds": self.cloned,
                # the examples the next cloning round fits, DAgger's labels among them; dropped once cloned
                "cloning_set": self.cloning_set if self.cloned < self.rounds else None,
                "in_progress": {
                    **self.current.state_dict(),
                    "return": self.ep_return,
                    "window": self.window.state_dict(),
                    "losses": dict(self.losses),
                },
            },
            best=best,
        )

    def clone_rounds(self) -> None:
        """The cloning rounds still to do (each saved: a stop waits for the round to end, and resumes after it)."""
        run_ = self.run_
        if self.cloning_set is None:
            self.cloning_set = (self.demos.obs[: len(self.demos)], self.demos.actions[: len(self.demos)])
        resumed_at = self.cloned * self.hp.bc_pretrain_steps if run_.state is not None else None
        pretrain_writer = run_.side_writer("pretrain", purge_step=resumed_at)
        while self.cloned < self.rounds and not run_.stop.requested:
            self.cloning_set = cloning_round(
                self.cfg,
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

    def start(self):
        """The episode in progress: the checkpoint's, replayed to its step, or a new one."""
        run_ = self.run_
        progress = run_.state.get("in_progress") if run_.state is not None else None
        if progress and len(progress["actions"]):
            obs, info = self.current.resume(progress, run_.last)
            self.ep_return = progress["return"]
            self.window.load_state_dict(progress["window"])
            self.losses = dict(progress["losses"])
            return obs
        obs, info = self.current.reset(**reset_options(self.typed, self.episode))
        self.ep_return = 0.0
        return obs

    def act_and_learn(self, obs):
        """One step: act, store its n-step transitions, update; at an episode's end, log it and start the next.
        Returns the next observation."""
        hp, agent, buffer, run_ = self.hp, self.agent, self.buffer, self.run_
        action = agent.random_action() if self.step < hp.warmup_steps else agent.act(obs, explore=True)
        next_obs, r, terminated, truncated, info = self.current.step(action)
        self.window.store(buffer, obs, action, r * hp.reward_scale, next_obs, terminated, truncated)
        obs = next_obs
        self.ep_return += r
        self.step += 1
        if self.step > hp.warmup_steps and len(buffer) >= hp.batch_size:
            self.losses = agent.update(mixed_batch(buffer, self.demos, hp.batch_size, hp.demo_share, agent.rng))
            for key in ("critic_loss", "actor_loss"):
                if key in self.losses:
                    check_finite(self.losses[key], key.replace("_", " "), self.step, run_.last)
        if terminated or truncated:
            o = info["outcome"]
            self.history.append({k: o[k] for k in OUTCOME_KEYS} | {"return": self.ep_return, "hazard": o["hazard"]})
            rolling = log_episode(run_.writer, self.history, o, self.ep_return, len(self.current), self.step)
            self.episode += 1
            # the next episode starts before any save, so that a checkpoint here holds no finished one
            obs, info = self.current.reset(**reset_options(self.typed, self.episode))
            self.ep_return = 0.0
            if self.step > hp.warmup_steps and len(self.history) >= min(ROLLING, 20) and rolling > self.best_return:
                self.best_return = rolling
                self.snapshot(best=True)
        return obs

    def train(self) -> dict:
        from tqdm import tqdm

        agent_id, hp = self.agent_id, self.hp
        with TrainingRun.for_agent(self.cfg, agent_id) as run_:
            self.run_ = run_
            if run_.state is not None:
                self.resume(run_)
            if self.cloned < self.rounds:
                self.clone_rounds()
            writer = run_.writer
            obs = self.start()
            t0, steps_this_run = time.perf_counter(), 0
            with tqdm(total=hp.total_steps, initial=self.step, desc=f"agent {agent_id.reward}", unit="step") as bar:
                while self.step < hp.total_steps and not run_.stop.requested:
                    obs = self.act_and_learn(obs)
                    steps_this_run += 1
                    bar.update(1)
                    if self.losses and self.step % 50 == 0:
                        for k, v in self.losses.items():
                            writer.add_scalar(f"train/{k}", v, self.step)
                        rate = steps_this_run / (time.perf_counter() - t0)
                        writer.add_scalar("speed/steps_per_s", rate, self.step)
                    if self.step % hp.checkpoint_every == 0:
                        self.snapshot()
            self.snapshot()
            self.env.close()
            if run_.stop.requested:
                return run_.stopped(self.step)
            return run_.finish(self.metrics(round(steps_this_run / (time.perf_counter() - t0), 1)))

    def metrics(self, steps_per_s: float) -> dict:
        recent = list(self.history)
        metrics = {
            "reward": self.agent_id.reward,
            "steps": self.step,
            "episodes": self.episode,
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
            self.step,
            self.episode,
            metrics["rolling_return"],
            self.run_.dir,
        )
        return metrics


def cloning_round(cfg, agent, encoder, action_map, cloning_set, held_out, round_: int, run_, writer, demo_info: dict):
    """Cloning round ``round_`` (0: the planner's demonstrations; from 1, DAgger: its labels on the student's own
    states join them first). Returns the examples the round fitted; ``demo_info`` gains the round's figures."""
    inputs, targets = cloning_set
    name, hp = run_.name, agent.cfg
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
