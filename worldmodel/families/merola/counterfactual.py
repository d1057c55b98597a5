"""The counterfactual-cost Q-learner on family merola (``agent=counterfactual_merola``): Merola et al.'s nine
actions on the same frames, their values fitted to the exact returns the simulator gives each action instead of
bootstrapped from sparse rewards.

    python -m worldmodel.train_agent experiment=NAME agent=counterfactual_merola [seed=K]

Merola's Double DQN ranks its nine actions at chance on its own states (docs/results/merola/: pairwise order 0.53
to 0.65 against re-simulated returns), and under Huber's loss a crash's size never reaches its gradient. This
learner keeps the DQN's action set and greedy policy, and takes its targets from re-simulation: the rounds, the
ensemble critic and its pessimism are ``worldmodel/counterfactual.py``'s (``train_rounds``), shared with the street's
and Kim's learners.

* **Actions**: Merola's nine, {brake, none, throttle} x {left, straight, right} (``system.ACTIONS``), each held as
  a shift (``envs/counterfactual.py``): the action for ``hold_s``, its steer mirrored as long, then braking that
  lets go at a standstill. The learner picks one at each of ``decisions`` decisions, ``interval_s`` apart; the
  last runs to its end. Merola's agent picks one every 0.1 s: the deviation that lets exact returns cover what it
  can do, as Kim's shifts do (docs/design.md §10).
* **Labels**: at every decision, each of the nine re-simulated on the camera-less twin to the end of the episode,
  the best of the nine taking over at the next decision; the label is minus the run's reward (``merola_safe`` in
  the preset, a named deviation: a crash outweighs any progress). Round 0's episodes are driven by braking, shared
  by the seeds, in ``data/NAME/merola_counterfactual_labels/``; a DAgger round's by the learner, in the run folder.
* **States**: what ``ddqn_merola`` sees (``obs``: the frozen VAE's means of the last 4 frames by default, or the true
  state), and the decision's index.
* **Critic**: each action joins the state as a code of its own (``CODES``: one unit per action, braking none), not
  as its shift parameters.
* **Policy**: at each decision, the action of lowest pessimistic predicted cost (``counterfactual.choose``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from envs.counterfactual import ShiftPolicy, ShiftSpace, brake_decision, label_episode
from envs.merola import sample as sample_merola
from envs.privileged import PRIVILEGED_DIM
from envs.streams import MEROLA_COUNTERFACTUAL_LABELS

from ... import artifacts
from ...common import StageError, seed_everything, set_threads
from ...counterfactual import critic_decision, critic_from_state, train_rounds
from ...counterfactual_labels import held_out_rows
from ...counterfactual_shards import label_parts, shard_labels
from ...models.counterfactual import features
from .system import ACTIONS, family_env, observer

log = logging.getLogger(__name__)
KEYS = ("t", "u", "costs", "static", "chosen", "view")
# the nine actions as shift parameters u (ShiftSpace): the steer, the pedal as a residual on full braking
# (p = -1 + 2 u[1]); the hold is the preset's one length, so u[2] is unused. (0, 0, 0) is straight-line braking
CHOICES = np.array([(steer, (pedal + 1.0) / 2.0, 0.0) for steer, pedal in ACTIONS], dtype=np.float32)
# what the critic reads of an action: a unit of its own for each of the eight that are not braking (all zero, as
# braking's u is), as a DQN's output per action. Read as the shift parameters instead, the critic's smooth fit over
# the 3 x 3 grid misplaces its corners (docs/results/merola/counterfactual/)
BRAKING = int(np.flatnonzero(~CHOICES.any(1))[0])
CODES = np.delete(np.eye(len(CHOICES), dtype=np.float32), BRAKING, axis=1)


class FrameView:
    """A ``ShiftPolicy``'s view on family merola: ``ddqn_merola``'s observer (frames or the true state) on the
    episode's env (``bind``)."""

    def __init__(self, see):
        self.see, self.env = see, None
        self.dim, self.needs_camera = see.dim, bool(getattr(see, "camera", True))

    def bind(self, env) -> None:
        self.env = env

    def reset(self) -> None:
        self.see.reset(None)

    def encode(self, obs) -> np.ndarray:
        return self.see(self.env, obs)

    def note_action(self, action) -> None:
        self.see.note_action(action)


def space(hold_s: float, step_s: float) -> ShiftSpace:
    """Every action held ``hold_s`` seconds, its final braking letting go at a standstill (Merola's reward charges
    braking below 2 m/s)."""
    return ShiftSpace((float(hold_s), float(hold_s)), float(step_s), release=True)


def shift_policy(shifts: ShiftSpace, decide, decisions: int, interval: int, see, name: str) -> ShiftPolicy:
    return ShiftPolicy.on_view(shifts, decide, decisions, interval, FrameView(see), name)


def hold_problem(c) -> None:
    if float(c.hold_s[0]) != float(c.hold_s[1]):
        raise StageError(
            f"agent.counterfactual.hold_s={list(c.hold_s)}: the nine actions are held one length; set both the same"
        )


def label_settings(cfg, typed, reward: str) -> dict:
    """What round 0's labels depend on: the decisions, the hold, the view, the reward and the env (not the training
    seed)."""
    from ...config import section

    c = typed.agent.counterfactual
    return {
        "version": 1,
        "family": "merola",
        "decisions": c.decisions,
        "interval": c.interval(typed.env.step_s),
        "hold_s": float(c.hold_s[0]),
        "reward": reward,
        "obs": typed.agent.obs,
        "view": observer_settings(cfg, typed.agent.obs),
        "env": section(cfg, "env"),
    }


def observer_settings(cfg, obs: str) -> dict:
    """The view's identity: the frozen VAE's digest for the frames, nothing else for the true state."""
    if obs != "frames_vae":
        return {"obs": obs, "resnet_weights": cfg.agent.merola.resnet_weights if obs == "frames_resnet" else None}
    return {"obs": obs, "vae": artifacts.vae_id(cfg)}


def labels_dir(cfg, typed, reward: str, round_: int, run_dir: Path) -> Path:
    if round_ > 0:
        return Path(run_dir) / "labels" / f"round{round_}"
    seed = typed.agent.counterfactual.label_seed
    settings = label_settings(cfg, typed, reward)
    name = f"{artifacts.config_sha256(settings)[:10]}-seed{typed.seed if seed is None else seed}"
    return artifacts.data_dir(cfg) / "merola_counterfactual_labels" / name


def label_shard(cfg, typed, reward: str, round_: int, first: int, stop: int, decide) -> dict:
    """Episodes ``first`` .. ``stop`` - 1 of round ``round_``, driven by ``decide`` (braking or the learner), the
    nine actions labelled at each decision."""
    c = typed.agent.counterfactual
    seed = typed.seed if c.label_seed is None else c.label_seed
    see = observer(cfg, typed.agent.obs)
    env = family_env(cfg, camera=bool(getattr(see, "camera", True)), reward=reward)
    twin = env.planning_twin()
    shifts = space(c.hold_s[0], env.step_s)
    policy = shift_policy(shifts, decide, c.decisions, c.interval(env.step_s), see, "labelling")
    nine = [shifts.shift(u) for u in CHOICES]
    parts = []
    for e in range(first, stop):
        spec = sample_merola(np.random.default_rng([seed, MEROLA_COUNTERFACTUAL_LABELS, round_, e]))
        parts.append(label_episode(env, spec, policy, lambda d, chosen: CHOICES, nine, twin, reward, False, None))
    env.close()
    return label_parts(parts, first, KEYS)


class NineActionLabels:
    """Family merola's labelled rounds as the states the shared rounds (``train_rounds``) fit on: ``ddqn_merola``'s
    view and the decision's index, for the critic; ``choices`` the nine actions, so that the policy is the critic's
    choice among them. No true-state heads (``aux_weight`` 0)."""

    def __init__(self, cfg, typed, reward: str, run_dir):
        self.cfg, self.typed, self.reward, self.run_dir = cfg, typed, reward, run_dir
        c = typed.agent.counterfactual
        if c.aux_weight:
            raise StageError("the nine-action learner has no true-state heads: set agent.counterfactual.aux_weight=0")
        if c.critic_obs != "actor":
            raise StageError(
                "the nine-action critic reads the policy's view: set agent.counterfactual.critic_obs=actor"
            )
        hold_problem(c)
        see = observer(cfg, typed.agent.obs)
        self.in_dim = self.critic_in = see.dim + 1
        self.choices, self.u_dim = CODES, CODES.shape[1]
        self.settings = {
            "learner": "counterfactual",
            "family": "merola",
            "in_dim": self.in_dim,
            "critic_in_dim": self.critic_in,
            "critic_members": c.critic_members,
            "critic_hidden": list(c.critic_hidden),
            "critic_obs": typed.agent.obs,
            "pessimism": float(c.pessimism),
            "anchor_weight": float(c.anchor_weight),
            "choices": CODES.tolist(),
            "shifts": CHOICES.tolist(),
            "critic_u_dim": int(CODES.shape[1]),
            "decisions": c.decisions,
            "interval": c.interval(typed.env.step_s),
            "hold_s": float(c.hold_s[0]),
            "step_s": float(typed.env.step_s),
            "obs": typed.agent.obs,
            "obs_dim": see.dim,
        }

    def round_data(self, round_: int, n: int, driver: dict | None, stop) -> dict | None:
        decisions = self.typed.agent.counterfactual.decisions
        decide = brake_decision if driver is None else decision(driver)
        if driver is None and round_ > 0:
            decide = None  # only reads what an earlier policy of this run labelled
        directory = labels_dir(self.cfg, self.typed, self.reward, round_, self.run_dir)
        shard = None
        if decide is not None:

            def shard(first: int, last: int) -> dict:
                return label_shard(self.cfg, self.typed, self.reward, round_, first, last, decide)

        settings = label_settings(self.cfg, self.typed, self.reward) if round_ == 0 else None
        what = f"merola counterfactual labels (round {round_})"
        data = shard_labels(directory, n, shard, KEYS, what, settings, stop)
        if data is None:
            return None
        d = np.concatenate([np.arange(k) for k in np.unique(data["episode"], return_counts=True)[1]])
        data["x"] = data["xc"] = features(data["view"], d, decisions)
        data["u"], data["chosen"] = codes(data["u"]), codes(data["chosen"])
        data["state"] = np.zeros((len(d), PRIVILEGED_DIM), np.float32)
        data["held"] = held_out_rows(data["episode"])
        return data


def codes(u: np.ndarray) -> np.ndarray:
    """The critic's code (``CODES``) of each of the nine actions' shift parameters in ``u`` (..., 3)."""
    match = (np.abs(np.asarray(u)[..., None, :] - CHOICES) < 1e-6).all(-1)
    if not match.any(-1).all():
        raise StageError("the labels hold other shifts than the nine actions': label them again")
    return CODES[match.argmax(-1)]


def decision(state: dict):
    """``decide(x, d)``: the choice of the critic in ``state`` (a checkpoint, or a DAgger round's driver)."""
    objective = SimpleNamespace(pessimism=float(state["pessimism"]), anchor_weight=float(state["anchor_weight"]))
    choices, shifts = (np.asarray(state[k], np.float32) for k in ("choices", "shifts"))
    return critic_decision(critic_from_state(state), choices, int(state["decisions"]), objective, shifts)


def train(cfg, run_, agent_id, typed) -> dict:
    """``train_agent agent=counterfactual_merola``: the shared rounds on the nine actions' labelled states."""
    set_threads(typed.threads)
    seed_everything(typed.seed)  # the checkpoint saves the process-wide generators' state: make it the seed's
    return train_rounds(typed, run_, agent_id.reward, NineActionLabels(cfg, typed, agent_id.reward, run_.dir))


def policy(cfg, state: dict, name: str) -> ShiftPolicy:
    """A trained checkpoint as a policy of the evaluation's interface, on the view it was trained with."""
    see = observer(cfg, state["obs"])
    if see.dim != int(state["obs_dim"]):
        raise StageError(
            f"{name} was trained on inputs of size {state['obs_dim']}, the observation {state['obs']} gives {see.dim} "
            "(the VAE changed?): retrain it"
        )
    shifts = space(state["hold_s"], state["step_s"])
    return shift_policy(shifts, decision(state), int(state["decisions"]), int(state["interval"]), see, name)
