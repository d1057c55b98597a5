"""Phase 3: DDPG acting from [z_t, zhat_{t+1}] in the live simulator, with reward R1 or R2.

    python -m worldmodel.train_agent experiment=NAME reward=r1|r2 scale=...
    python -m worldmodel.train_agent -m experiment=NAME reward=r1,r2        # both, through Hydra multirun

Episodes are the paper's scenarios (section IV-A, including ones with no hazard, where the policy must do no
harm), truncated ``env.horizon_after_ttc_s`` after the TTC. The reward is 0 except on the step of a collision
(R1 = -people involved, R2 = -sum of injury probabilities), exactly as in the paper.

    python -m worldmodel.train_agent -m experiment=NAME reward=r1,r2 seed=0,1,2   # a seed sweep

Writes ``runs/NAME/agent_r1/seed0/`` (reward, then training seed): ``last.pt`` (actor, critic, targets, optimisers, replay buffer,
step, RNG) every ``agent.checkpoint_every`` steps, ``best.pt`` (best rolling return), TensorBoard (episodic return,
collision rate by kind, injury sums, losses, Q, steps/s) and ``metrics.json`` when finished. A resumed run starts
a fresh episode at the saved step; the buffer and all optimiser state carry over.
"""
from __future__ import annotations

import json
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from .common import StageError, atomic_write_text, check_finite, hydra_main, positive, runs_dir, seed_everything, set_threads
from .training import Checkpoints, GracefulStop, tensorboard

ROLLING = 100


def agent_dir(cfg, reward: str | None = None, seed: int | None = None) -> Path:
    """``runs/NAME/agent_r1/seed0``: one directory per reward and training seed, so seed sweeps sit side by side."""
    return runs_dir(cfg, f"agent_{reward or cfg.reward.name}") / f"seed{int(cfg.seed if seed is None else seed)}"


def trained_agents(cfg) -> list[tuple[str, int]]:
    """(reward, training seed) of every agent of the experiment that has a checkpoint, sorted."""
    found = []
    for path in Path(cfg.paths.runs).glob("agent_r*/seed*/last.pt"):
        reward, seed = path.parent.parent.name.removeprefix("agent_"), path.parent.name.removeprefix("seed")
        if reward in ("r1", "r2") and seed.isdigit():
            found.append((reward, int(seed)))
    return sorted(found)


def validate_config(cfg) -> None:
    if cfg.reward.name not in ("r1", "r2"):
        raise StageError(f"config reward.name={cfg.reward.name!r} is unknown: use reward=r1 or reward=r2")
    positive(cfg.agent, "total_steps", "batch_size", "buffer_size", "checkpoint_every", "gamma", "tau",
             "actor_lr", "critic_lr", where="agent")
    if cfg.agent.warmup_steps < 0 or cfg.agent.exploration_noise < 0:
        raise StageError("config agent.warmup_steps and agent.exploration_noise must be >= 0")
    if not 0 < cfg.agent.gamma <= 1 or not 0 < cfg.agent.tau <= 1:
        raise StageError(f"config agent.gamma={cfg.agent.gamma} and agent.tau={cfg.agent.tau} must be in (0, 1]")


def make_env(cfg, camera: bool = True):
    from envs import UrbanCollisionEnv

    e = cfg.env
    return UrbanCollisionEnv(camera=camera, image_size=int(e.image_size), fov_deg=float(e.fov_deg),
                             reward=str(cfg.reward.name), horizon_after_ttc_s=float(e.horizon_after_ttc_s),
                             mu=float(e.mu), occupants_per_car=int(e.occupants_per_car))


def load_world_model(cfg):
    from .agent_obs import WorldModelEncoder
    from .train_rnn import load_rnn
    from .train_vae import load_vae

    vae, _ = load_vae(cfg, "best")
    rnn, _ = load_rnn(cfg, "best")
    return WorldModelEncoder(vae, rnn, use_speed=bool(cfg.agent.use_speed))


def load_actor(cfg, reward: str, which: str = "last", seed: int | None = None):
    """The trained actor for ``reward`` and training ``seed`` (default ``cfg.seed``), in eval mode."""
    from .common import load_checkpoint
    from .models.ddpg import Actor

    path = agent_dir(cfg, reward, seed) / f"{which}.pt"
    state = load_checkpoint(path, f"{reward} agent checkpoint", "train_agent", cfg)
    actor = Actor(state["obs_dim"], 2, tuple(state["actor_hidden"]))
    actor.load_state_dict(state["agent"]["actor"])
    return actor.eval(), state


def episode_seed(seed: int, episode: int) -> int:
    return int(np.random.default_rng([seed, 1729, episode]).integers(0, 2**31 - 1))


def run(cfg) -> dict:
    from .agent_obs import WorldModelView
    from .models.ddpg import DDPG, DDPGConfig, ReplayBuffer

    validate_config(cfg)
    set_threads(cfg.threads)
    reward = str(cfg.reward.name)
    out = agent_dir(cfg)
    encoder = load_world_model(cfg)
    env = WorldModelView(make_env(cfg), encoder)
    ckpts = Checkpoints(out, "train_agent", cfg)
    if (out / "metrics.json").exists() and not cfg.resume:
        raise StageError(f"{out} holds a finished agent. Pass resume=true to keep it, or delete {out}.")

    seed_everything(int(cfg.seed))
    dcfg = DDPGConfig.from_mapping(cfg.agent)
    obs_dim = encoder.dim
    agent = DDPG(obs_dim, 2, dcfg, seed=int(cfg.seed))
    buffer = ReplayBuffer(dcfg.buffer_size, obs_dim, 2)
    step, episode, best_return = 0, 0, -float("inf")
    history: deque = deque(maxlen=ROLLING)
    state = ckpts.resume_state(bool(cfg.resume))
    if state is not None:
        if state["obs_dim"] != obs_dim:
            raise StageError(f"{ckpts.last} expects agent inputs of size {state['obs_dim']}, the world model gives "
                             f"{obs_dim} (vae.latent_dim / agent.use_speed changed); delete {out} to retrain")
        agent.load_state_dict(state["agent"])
        buffer.load_state_dict(state["buffer"])
        step, episode, best_return = state["step"], state["episode"], state["best_return"]
        history.extend(state["history"])
        print(f"[agent_{reward}] resuming from {ckpts.last}: step {step}, episode {episode}")

    total = int(cfg.agent.total_steps)

    def snapshot(best=False):
        ckpts.save({"agent": agent.state_dict(), "buffer": buffer.state_dict(), "step": step, "episode": episode,
                    "best_return": best_return, "history": list(history), "obs_dim": obs_dim,
                    "actor_hidden": list(dcfg.actor_hidden), "reward": reward}, best=best)

    from tqdm import tqdm

    writer = tensorboard(out, purge_step=step + 1 if state is not None else None)
    obs, info = env.reset(seed=episode_seed(int(cfg.seed), episode))
    ep_return, ep_len = 0.0, 0
    t0, steps_this_run = time.perf_counter(), 0
    losses = {}
    stopped = False
    with GracefulStop() as stop, tqdm(total=total, initial=step, desc=f"agent {reward}", unit="step") as bar:
        while step < total:
            if step < dcfg.warmup_steps:
                action = agent.random_action()
            else:
                action = agent.act(obs, explore=True)
            next_obs, r, terminated, truncated, info = env.step(action)
            buffer.add(obs, action, r, next_obs, terminated)
            obs = next_obs
            ep_return += r
            ep_len += 1
            step += 1
            steps_this_run += 1
            bar.update(1)

            if step > dcfg.warmup_steps and len(buffer) >= dcfg.batch_size:
                losses = agent.update(buffer.sample(dcfg.batch_size, agent.rng))
                check_finite(losses["critic_loss"], "critic loss", step, ckpts.last)
                check_finite(losses["actor_loss"], "actor loss", step, ckpts.last)

            if terminated or truncated:
                o = info["outcome"]
                history.append({k: o[k] for k in ("pedestrian_collision", "vehicle_collision", "static_collision",
                                                  "pedestrian_injury", "occupant_injury", "lane_departure")}
                               | {"return": ep_return, "hazard": o["hazard"]})
                writer.add_scalar("episode/return", ep_return, step)
                writer.add_scalar("episode/length", ep_len, step)
                writer.add_scalar("episode/pedestrian_injury", o["pedestrian_injury"], step)
                writer.add_scalar("episode/occupant_injury", o["occupant_injury"], step)
                for kind in ("pedestrian", "vehicle", "static"):
                    writer.add_scalar(f"collision_rate/{kind}", np.mean([h[f"{kind}_collision"] for h in history]), step)
                writer.add_scalar("episode/lane_departure_rate", np.mean([h["lane_departure"] for h in history]), step)
                rolling = float(np.mean([h["return"] for h in history]))
                writer.add_scalar("episode/return_rolling", rolling, step)
                episode += 1
                if step > dcfg.warmup_steps and len(history) >= min(ROLLING, 20) and rolling > best_return:
                    best_return = rolling
                    snapshot(best=True)
                obs, info = env.reset(seed=episode_seed(int(cfg.seed), episode))
                ep_return, ep_len = 0.0, 0

            if losses and step % 50 == 0:
                for k, v in losses.items():
                    writer.add_scalar(f"train/{k}", v, step)
                writer.add_scalar("speed/steps_per_s", steps_this_run / (time.perf_counter() - t0), step)
            if step % int(cfg.agent.checkpoint_every) == 0:
                snapshot()
            if stop.requested:
                stopped = True
                break
    snapshot()
    env.close()
    writer.close()
    if stopped:
        print(f"[agent_{reward}] stopped at step {step}; resume with resume=true")
        return {"stopped": True, "step": step}

    recent = list(history)
    metrics = {
        "reward": reward, "steps": step, "episodes": episode,
        "rolling_return": float(np.mean([h["return"] for h in recent])) if recent else None,
        "best_rolling_return": best_return if best_return > -float("inf") else None,
        "recent_collision_rate": {k: float(np.mean([h[f"{k}_collision"] for h in recent])) if recent else None
                                  for k in ("pedestrian", "vehicle", "static")},
        "steps_per_s": round(steps_this_run / (time.perf_counter() - t0), 1),
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2))
    print(f"[agent_{reward}] {step} steps, {episode} episodes; rolling return {metrics['rolling_return']}; "
          f"wrote {out}")
    return metrics


main = hydra_main("train_agent")(run)

if __name__ == "__main__":
    main()
