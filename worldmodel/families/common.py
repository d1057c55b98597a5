"""What every peer's trainer and evaluation share: resuming a DQN run, its training episodes, its checkpoint, and
writing an evaluation directory (``results.csv`` first, ``summary.json`` last, since its presence marks the
evaluation complete)."""

from __future__ import annotations

import copy
import csv
import dataclasses
import io
import json
import logging
import re
import time
from pathlib import Path

import numpy as np

from envs.chae import brake_action

from .. import artifacts
from ..common import StageError, atomic_write_text

log = logging.getLogger(__name__)


def dqn_config(cfg):
    """``agent.dqn`` as the typed ``DQNConfig``."""
    from omegaconf import OmegaConf

    from ..models.dqn import DQNConfig

    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(DQNConfig), cfg.agent.dqn))


class TrueStateView:
    """A peer learner's view of the true state instead of its own sensor (``agent.obs=privileged``; the diagnosis
    that separates the learner from its perception): ``envs.privileged.privileged_state``, the hazard car and
    pedestrian relative to the ego, the ego's motion and what blocks each escape corridor, read from the simulator.
    The observer interface of the families' views; no camera."""

    camera = False
    speed = False  # the ego's speed is in the vector already

    def __init__(self):
        from envs.privileged import PRIVILEGED_DIM

        self.dim = PRIVILEGED_DIM

    def reset(self, seed=None) -> None:
        pass

    def __call__(self, env, obs=None) -> np.ndarray:
        from envs.privileged import privileged_state

        return privileged_state(env)

    def note_action(self, action) -> None:
        pass


class DQNPolicy:
    """A trained DQN, greedy, behind the scripted-policy interface; its actions are Chae's brake levels unless
    ``action_of`` maps them (Merola's steer and pedal grid)."""

    def __init__(self, name: str, agent, see, policy_seed: int, action_of=None):
        self.name, self.agent, self.see, self.policy_seed = name, agent, see, policy_seed
        self.action_of = brake_action if action_of is None else action_of  # action index -> [steer, pedal]

    def reset(self, seed=None) -> None:
        self.see.reset(seed)

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        action = self.action_of(self.agent.act(self.see(self.env, obs), explore=False))
        self.see.note_action(action)
        return action


def resume_dqn(run_, learner, obs_dim: int, curve: dict) -> tuple[int, dict]:
    """(episode, curve) to continue from: the run's checkpoint loaded into ``learner`` (a ``DQNLearner``), or
    (0, ``curve``) when fresh. Refuses a checkpoint whose input size is not the observation's."""
    if run_.state is None:
        return 0, curve
    if run_.state["obs_dim"] != obs_dim:
        raise StageError(
            f"{run_.last} expects inputs of size {run_.state['obs_dim']}, the observation gives {obs_dim}; "
            f"delete {run_.dir} to retrain"
        )
    learner.load_state_dict(run_.state)
    episode = int(run_.state["episode"])
    run_.resumed(f"episode {episode}")
    return episode, run_.state["curve"]


class DQNEpisodes:
    """A peer family's training episodes for a DQN learner (``learners.loop.Episodes``): episode k's scenario and
    the observer's noise seed are ``scenario_of(k)``; an action index becomes the simulator's [steer, pedal]
    through ``action_of``, which the observer notes."""

    def __init__(self, env, see, scenario_of, action_of):
        self.env, self.see, self.scenario_of, self.action_of = env, see, scenario_of, action_of

    def start(self, episode: int):
        spec, view_seed = self.scenario_of(episode)
        obs, _ = self.env.reset(options={"scenario": spec})
        self.see.reset(view_seed)
        return self.see(self.env, obs)

    def step(self, action_index) -> tuple:
        action = self.action_of(action_index)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.see.note_action(action)
        return self.see(self.env, obs), reward, terminated, truncated, info


def dqn_checkpoint(learner, hp, episode: int, curve: dict, obs: str, obs_dim: int, reward: str, **extra) -> dict:
    """A dqn run's ``last.pt``: network, optimiser, memories and RNG (the ``DQNLearner``'s state), the learning
    curve, and what ``load_policy`` needs to rebuild it (observation, its size, the hyperparameters)."""
    return {
        **learner.state_dict(),
        "episode": episode,
        "step": learner.steps,
        "log_step": episode,  # its TensorBoard curves count episodes: a resumed run purges what came after this
        "curve": curve,
        "obs": obs,
        "obs_dim": obs_dim,
        "learner": "dqn",
        "dqn_config": dataclasses.asdict(hp),
        "reward": reward,
        **extra,
    }


MODEL_HASH_COLUMNS = ("vae_sha", "rnn_sha", "actor_sha")  # as the paper's rows carry them (report.MODEL_COLUMNS)


def write_rows(out: Path, rows: list[dict], columns, cfg=None, record: dict | None = None) -> None:
    """``results.csv``: ``columns``, then, given the evaluation's ``cfg`` and provenance ``record``, each trained
    policy's model hashes (``models_of``: the VAE and the LSTM it sees through, its own checkpoint), so that every
    row can be tied to the models that made it, as the ledger ties its test-bank row."""
    columns = list(columns)
    if cfg is not None and record is not None:
        hashes: dict[str, dict] = {}
        for r in rows:
            key = f"{r['policy']}/seed{r['policy_seed']}"
            if str(r["policy"]).startswith("agent_") and key not in hashes:
                hashes[key] = models_of(cfg, key, record["inputs"].get(key))
            models = hashes.get(key, {})
            r.update({c: models.get(c.removesuffix("_sha"), "") for c in MODEL_HASH_COLUMNS})
        columns += [c for c in MODEL_HASH_COLUMNS if c not in columns]
    text = io.StringIO(newline="")  # the csv module's own line ends, as a file opened with newline="" keeps them
    w = csv.DictWriter(text, fieldnames=columns)
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(out / "results.csv", text.getvalue())  # a reader sees the old rows or all the new ones


def drawn(typed, family: str):
    """The typed section of ``typed`` (``validate(cfg)``) that draws ``family``'s bank (``evaluate.<section>``, or
    ``evaluate`` itself for a family without a section: ``Family.validation_seed_key`` names it), with its validation
    seed replaced by the seed of the bank ``evaluate.bank`` names: its own (a validation draw) or the family's sealed
    test seed (worldmodel/banks.py). A copy with the seed set, not ``dataclasses.replace``: building the section
    anew would refuse a test seed."""
    from .. import registry
    from ..banks import draw_seed

    f = registry.family(family)
    *path, leaf = (f.validation_seed_key or f"evaluate.{f.section}.seed").split(".")
    section = typed
    for part in path:
        section = getattr(section, part)
    c = copy.copy(section)
    setattr(c, leaf, draw_seed(typed.evaluate.bank, family, getattr(c, leaf)))
    return c


@dataclasses.dataclass
class Driven:
    """What a family's evaluation drove: every row, the family's trained agents, and how many trials and policies."""

    rows: list[dict]
    agents: list
    trials: int
    policies: int


def evaluation(cfg, family: str, columns, drive, report, train_with: str, folder=None, write=None) -> dict:
    """The evaluation every family fills in (``evaluate.family=<family>``): its bank, drawn for ``evaluate.bank``
    from the section ``drawn`` gives; ``drive(cfg, c) -> Driven``, every policy on the same trials (each loaded
    before the first trial runs); the rows, with each trained policy's model hashes; ``report(cfg, c, driven, out)
    -> (summary, headline)``, its tables, figures and TensorBoard; on the test bank a ledger row; then provenance
    and ``summary.json``, last. ``train_with``: the preset that trains the family's agents, for the hint when there
    are none; ``folder(c)``: a suffix of the evaluation's folder for a draw the bank's seed does not tell;
    ``write(out, rows)``: the family's own rows file, whose rows carry their model hashes already (default: ``columns``
    with the hashes added, ``write_rows``)."""
    from ..config import validate

    c = drawn(validate(cfg), family)
    out = artifacts.eval_dir(cfg)
    out = out.with_name(out.name + (folder(c) if folder else ""))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    record = artifacts.provenance(cfg, "eval")
    done = drive(cfg, c)
    if not done.agents:
        log.info(
            "[eval %s] no agents of the family under %s. Train one with "
            "`python -m worldmodel.train_agent experiment=%s agent=%s`.",
            family,
            artifacts.runs_root(cfg),
            cfg.experiment,
            train_with,
        )
    if write is None:
        write_rows(out, done.rows, columns, cfg, record)
    else:
        write(out, done.rows)
    summary, headline = report(cfg, c, done, out)
    record_if_test(cfg, family, done.rows, record, headline)
    seal(out, summary, record, t0)
    log.info(
        "[eval %s] %d scenarios x %d policies in %.0f s: %s",
        family,
        done.trials,
        done.policies,
        summary["wall_s"],
        out / "tables.md",
    )
    return summary


def seal(out: Path, summary: dict, record: dict, t0: float) -> dict:
    """Provenance, the wall time, then ``summary.json``: last, because it marks the evaluation complete."""
    artifacts.write_provenance(out, record)
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    return summary


ENSEMBLE_KEY = re.compile(r"^(?P<policy>agent_.+)_ensemble(?P<k>\d+)/seed(?P<group>\d+)$")  # chae/policies.ensembles


def models_of(cfg, key: str, actor: str | None = None) -> dict[str, str | None]:
    """A trained agent's short model hashes for the ledger: the world model it sees through (the VAE alone for
    frozen-VAE frames, the VAE and the LSTM for the world model's observation), then its own checkpoint (``actor``,
    the evaluation's record of it; read from disk for an agent of another family, such as the paper's agents)."""
    from ..config import agent_preset

    ensemble = ENSEMBLE_KEY.match(key)
    if ensemble:  # Chae's ensemble k of group g: its members are seeds g*k .. g*k+k-1 of the policy
        k, group = int(ensemble["k"]), int(ensemble["group"])
        members = (models_of(cfg, f"{ensemble['policy']}/seed{s}")["actor"] for s in range(group * k, group * k + k))
        return {"members": "+".join(m or "-" for m in members)}
    agent = artifacts.AgentId.parse(key)
    actor = actor or artifacts.actor_id(cfg, agent)
    obs = agent.obs or agent_preset(cfg, agent.variant).obs
    models = {}
    if obs in ("worldmodel", "frames_vae"):
        models["vae"] = artifacts.short(artifacts.vae_id(cfg))
    if obs == "worldmodel":
        models["rnn"] = artifacts.short(artifacts.rnn_id(cfg))
    return {**models, "actor": artifacts.short(actor)}


def record_if_test(cfg, family: str, rows: list[dict], record: dict, headline: dict[str, str]) -> None:
    """On the sealed test bank, a ledger row: every policy of ``rows`` (trained ones with their models' hashes,
    ``models_of``) and its headline figure."""
    from ..banks import ledger_key, record_evaluation

    policies: dict[str, dict] = {}
    for r in rows:
        trained = str(r["policy"]).startswith("agent_")
        key = ledger_key(r)
        if key not in policies:
            policies[key] = models_of(cfg, key, record["inputs"].get(key)) if trained else {}
    first = (rows[0]["policy"], rows[0]["policy_seed"]) if rows else None
    scenarios = sum(1 for r in rows if (r["policy"], r["policy_seed"]) == first)  # every policy runs them all
    record_evaluation(cfg, family, artifacts.eval_dir(cfg) / "results.csv", scenarios, policies, headline)


def world_model_step_s(typed) -> float:
    """The step length the experiment's world model was trained at, at which its agents act on any family: the
    env section's of the typed config ``typed`` when it describes the paper's family, else the paper's 1/15 s."""
    return typed.env.step_s if typed.env.family == "porav" else 1.0 / 15.0
