"""Chae's DQN training on family chae (``train_agent`` with ``agent.learner=dqn``): the episodes, the validations
and checkpoints along the way, the rescoring at the end and the extension blocks it may ask for."""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from envs.chae import BRAKE_LEVELS, TTC_RANGE, ChaeSpec, brake_action, sample_chae
from envs.streams import CHAE_TRAINING_EPISODES

from ...artifacts import AgentId
from ...common import StageError, atomic_torch_save, atomic_write_bytes, percent, resolve_device
from ...learners.dqn import DQNLearner
from ...learners.loop import Callbacks, TrainingLoop
from ..common import DQNEpisodes, DQNPolicy, dqn_checkpoint, dqn_config, resume_dqn
from .observe import HistoryObserver, family_env, observer
from .report import ROLLING
from .select import Validation, member_found, rescore_kept, selected, validated_path

log = logging.getLogger(__name__)
CHECKPOINT_EPISODES = 100


def episode_scenario(seed: int, episode: int, ttc_range=TTC_RANGE) -> tuple[ChaeSpec, int]:
    """Training episode ``episode``'s scenario and observation-noise seed: a function of (seed, episode) and the
    TTC range (``agent.chae.ttc_range``) only, so a resumed run draws what an uninterrupted one would."""
    rng = np.random.default_rng([int(seed), CHAE_TRAINING_EPISODES, int(episode)])
    return sample_chae(rng, ttc_range=(float(ttc_range[0]), float(ttc_range[1]))), int(rng.integers(2**31))


def bumped(terminated: bool, info: dict) -> bool:
    """Chae's trauma: the transition into a bump, which ends the episode."""
    return terminated and info["outcome"]["end"] == "bump"


def check_settings(typed, agent_id: AgentId) -> None:
    """Refuse a dqn run that is not Chae's braking, or whose checkpoint selection would draw the evaluation's
    trials."""
    if agent_id.reward != "chae":
        raise StageError(
            f"agent.learner=dqn learns Chae's braking with reward chae, not {agent_id.reward}: use agent=dqn_chae"
        )
    sel = typed.agent.chae.select
    for key in ("seed", "rescore_seed") if sel.rescore else ("seed",):
        if sel.every and getattr(sel, key) == typed.evaluate.chae.seed:
            raise StageError(
                f"agent.chae.select.{key}={getattr(sel, key)} is the evaluation's draw (evaluate.chae.seed): "
                f"checkpoints must be chosen on other trials; give agent.chae.select.{key} another value"
            )


def train(cfg, run_, agent_id: AgentId) -> dict:
    """``train_agent`` for ``agent.learner=dqn``: ``agent.chae.episodes`` episodes of family chae."""
    from ...config import validate

    typed = validate(cfg)
    check_settings(typed, agent_id)
    return ChaeRun(cfg, typed, run_, agent_id).train()


class ChaeRun(Callbacks):
    """One dqn run on family chae: its learner, view and envs, the learning curve, the validations and rescorings."""

    def __init__(self, cfg, typed, run_, agent_id: AgentId):
        """``typed``: ``cfg`` validated."""
        from ...models.dqn import DQN

        self.cfg, self.typed, self.run_, self.agent_id = cfg, typed, run_, agent_id
        a = self.a = typed.agent
        self.sel = sel = a.chae.select
        self.see = see = observer(cfg, a.obs, noise_m=a.chae.noise_m)
        self.see_noise = see.view.noise_m if isinstance(see, HistoryObserver) else None  # what load_policy rebuilds
        self.env = family_env(cfg, see.camera)
        self.hp = dqn_config(cfg)
        agent = DQN(see.dim, len(BRAKE_LEVELS), self.hp, typed.seed, device=resolve_device(typed.device))
        self.learner, self.agent = DQNLearner(agent, trauma_of=bumped), agent
        episode, self.curve = resume_dqn(run_, self.learner, see.dim, {"return": [], "end": []})
        self.curve.setdefault("validation", [])
        self.first_validation = int(np.ceil(sel.start * a.chae.episodes))
        self.validation = Validation(sel, family_env(cfg, see.camera)) if sel.every else None
        self.recent: deque = deque(maxlen=ROLLING)
        self.recent.extend(e == "bump" for e in self.curve["end"][-ROLLING:])
        ttcs = a.chae.ttc_range
        episodes = DQNEpisodes(self.env, see, lambda k: episode_scenario(typed.seed, k, ttcs), brake_action)
        self.loop = TrainingLoop(self.learner, episodes, run_, self, episode=episode, bar_unit="episode")
        # episode -> its rescoring, per rescoring draw: a checkpoint is scored once, by a resumed run too
        draw = f"seed {sel.rescore_seed}, {sel.rescore_trials} trials, TTCs {sel.rescore_ttcs or [sel.ttcs[0]]}"
        self.rescore_cache: dict = self.curve.setdefault("rescorings", {}).setdefault(draw, {})

    def snapshot(self, best: bool = False, keep: bool = False) -> None:
        state = dqn_checkpoint(
            self.learner,
            self.hp,
            self.loop.episode,
            self.curve,
            self.a.obs,
            self.see.dim,
            self.agent_id.reward,
            noise_m=self.see_noise,
        )
        if keep:
            atomic_torch_save(state, validated_path(self.run_.dir, self.loop.episode))
        self.run_.save(state, best=best)

    def on_episode(self, loop, outcome: dict, ret: float, length: int) -> None:
        """A training episode logged; a validation (or a checkpoint) when one falls due."""
        typed, sel, curve, writer = self.typed, self.sel, self.curve, self.run_.writer
        end = outcome["end"]
        curve["return"].append(float(ret))
        curve["end"].append(end)
        self.recent.append(end == "bump")
        episode = loop.episode
        writer.add_scalar("episode/return", ret, episode)
        writer.add_scalar("episode/bump_rate_rolling", float(np.mean(self.recent)), episode)
        writer.add_scalar("train/epsilon", self.agent.epsilon(), episode)
        if "loss" in loop.losses:
            writer.add_scalar("train/loss", loop.losses["loss"], episode)
        if self.validation is not None and episode >= self.first_validation and episode % sel.every == 0:
            score = self.validation.score(DQNPolicy("validation", self.agent, self.see, typed.seed), episode)
            improved = selected(curve["validation"] + [score], sel.max_bump) is score
            curve["validation"].append(score)
            writer.add_scalar("validation/max_bump_rate", score["max_bump_rate"], episode)
            writer.add_scalar("validation/unnecessary_stop_rate", score["unnecessary_stop_rate"], episode)
            self.snapshot(best=improved, keep=sel.keep)
        elif episode % CHECKPOINT_EPISODES == 0:
            self.snapshot()

    def choose(self) -> tuple[dict | None, dict | None]:
        """The validation score best.pt holds and, with rescoring, the rescoring (best.pt then its choice)."""
        sel, curve, run_ = self.sel, self.curve, self.run_
        chosen, rescored = selected(curve["validation"], sel.max_bump), None
        if self.validation is not None and sel.rescore:
            rescored = rescore_kept(self.cfg, self.agent_id, run_.dir, curve["validation"], sel, self.rescore_cache)
            if rescored["chosen"] is not None:
                episode_chosen = rescored["chosen"]["episode"]
                atomic_write_bytes(run_.best, validated_path(run_.dir, episode_chosen).read_bytes())
                chosen = next(s for s in curve["validation"] if s["episode"] == episode_chosen)
        return chosen, rescored

    def train(self) -> dict:
        """The planned episodes, then whole blocks of ``select.extend`` until the rescoring finds a member inside
        both bars (at most ``extend_blocks``); the metrics, or the stopped run's."""
        from tqdm import tqdm

        sel, run_, loop, episodes = self.sel, self.run_, self.loop, self.a.chae.episodes
        # training on needs the rescoring's verdict: without validation (agent.chae.select.every=0) there is none
        block, blocks = (sel.extend, sel.extend_blocks) if self.validation is not None and sel.rescore else (0, 0)
        target = first_target(loop.episode, episodes, block)
        gates = self.curve.setdefault("gates", [])  # each rescoring's verdict: did it find a member inside both bars?
        run_.restore_random_state()  # building the networks and views drew from them
        with tqdm(total=target, initial=loop.episode, desc=f"dqn chae ({self.a.obs})", unit="episode") as bar:
            while True:
                loop.run(lambda end=target: loop.episode >= end, bar)
                if run_.stop.requested:
                    self.snapshot()
                    break
                chosen, rescored = self.choose()
                verdict = {"episode": loop.episode, "member": member_found(rescored, sel)}
                if gates and gates[-1]["episode"] == loop.episode:  # a finished run resumed: the same verdict again
                    gates.pop()
                gates.append(verdict)
                self.snapshot()  # with the rescoring and its verdict in the curve: a resumed run need not drive it
                if not block or target >= episodes + blocks * block or gates[-1]["member"]:
                    break
                log.info(
                    "[%s] no rescored member inside both bars at episode %d: %d more", run_.name, loop.episode, block
                )
                target += block
                bar.total = target
                bar.refresh()
        self.env.close()
        if self.validation is not None:
            self.validation.env.close()
        if run_.stop.requested:
            return run_.stopped(self.agent.steps)
        return self.metrics(chosen, rescored, gates)

    def metrics(self, chosen: dict | None, rescored: dict | None, gates: list[dict]) -> dict:
        last = self.curve["end"][-ROLLING:]
        return {
            "reward": self.agent_id.reward,
            "obs": self.a.obs,
            "episodes": self.loop.episode,
            "steps": self.agent.steps,
            "recent_bump_rate": float(np.mean([e == "bump" for e in last])) if last else None,
            "recent_stop_rate": float(np.mean([e == "stop" for e in last])) if last else None,
            "selected": chosen,
            "rescored": rescored,
            "extended": max(0, self.loop.episode - self.a.chae.episodes),
            "gates": gates,
            "curve": self.curve,
        }


def first_target(episode: int, episodes: int, block: int) -> int:
    """The episode a run at ``episode`` trains to before its next rescoring: the planned ``episodes``, or, for a run
    resumed inside an extension block of ``block`` episodes, that block's end."""
    if not block or episode <= episodes:
        return episodes
    return episodes + -(-(episode - episodes) // block) * block


def summary(metrics: dict) -> str:
    """One log line for a finished training run."""
    line = f"{metrics['episodes']} episodes; bumps in the last 100: {percent(metrics['recent_bump_rate'])}"
    chosen = metrics.get("selected")
    if chosen:
        line += (
            f"; best.pt = episode {chosen['episode']} (validation: bumps <= {chosen['max_bump_rate']:.1f} % per TTC, "
            f"{chosen['unnecessary_stop_rate']:.1f} % unnecessary stops)"
        )
    return line
