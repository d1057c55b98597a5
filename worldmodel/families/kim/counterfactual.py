"""The counterfactual-cost DDPG on family kim (``agent=counterfactual_kim``): Kim et al.'s LIDAR view, with the
critic fitted to the exact costs the simulator gives its manoeuvres instead of bootstrapped from sparse rewards.

    python -m worldmodel.train_agent experiment=NAME agent=counterfactual_kim [seed=K]

Kim's DDPG ranks manoeuvres near chance on its own states (docs/results/kim/, ``experiments/kim_critic_vs_exact``),
as the paper's DDPG did on the camera family; the counterfactual-cost actor fixed that there. This is the same
learner (``worldmodel/counterfactual.py``: the rounds, the ensemble critic, the pessimistic actor, the DAgger rounds
and the checkpoints are that module's) on this family's states:

* **States**: Kim's LIDAR view (``observe.LidarObserver``: the last scans and the previous action, recorded as the
  Kim action that asks for the controls taken), plus the decision's index.
* **Labels**: the shifts of ``envs/counterfactual.py`` re-simulated from each decision with ``shift_cost`` of
  Kim's ``kim_unaware`` cost (the summed ISS of the crashes to come), on training-distribution episodes
  (``training_scenario``, stream ``KIM_COUNTERFACTUAL_LABELS``). Round 0's, driven by braking, do not depend on the
  training seed and are kept for every seed in ``data/NAME/kim_counterfactual_labels/``; a DAgger round's, driven by
  the actor, in the run folder. Both in shards of ``SHARD`` episodes, so a stopped labelling resumes.
* **Acting**: a shift (steer, pedal, duration) at each decision, in our controls, not Kim's (desired speed,
  steering angle) per step: the deviation that lets exact labels cover what the actor can do (docs/design.md §10).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from envs.counterfactual import ShiftPolicy, brake_decision, label_episode
from envs.kim import kim_action_for
from envs.privileged import PRIVILEGED_DIM
from envs.streams import KIM_COUNTERFACTUAL_LABELS, KIM_COUNTERFACTUAL_PROPOSALS

from ... import artifacts
from ...common import StageError, seed_everything, set_threads
from ...counterfactual import train_rounds
from ...counterfactual_labels import actor_decision, held_out_rows, proposer
from ...counterfactual_shards import label_parts, shard_labels
from ...models.counterfactual import actor_from_state, features
from .observe import LidarObserver, family_env, observer, training_scenario

log = logging.getLogger(__name__)
REWARD = "kim_unaware"  # the cost whose zero is an avoided runner, as the LIDAR chooser's
KEYS = ("t", "u", "costs", "static", "chosen", "view")


class LidarView:
    """A ``ShiftPolicy``'s view on family kim: the LIDAR observer on the episode's env (``bind``), told each action
    taken as the Kim action that asks for it."""

    needs_camera = False

    def __init__(self, see: LidarObserver):
        self.see, self.env = see, None
        self.dim = see.dim

    def bind(self, env) -> None:
        self.env = env

    def reset(self) -> None:
        self.see.reset(None)

    def encode(self, obs) -> np.ndarray:
        return self.see(self.env)

    def note_action(self, action) -> None:
        self.see.note_action(kim_action_for(action, self.env.ego.v))


def shift_policy(space, decide, decisions: int, interval: int, see: LidarObserver, name: str) -> ShiftPolicy:
    """A shift at each of ``decisions`` decisions, ``interval`` steps apart, chosen by ``decide(x, d)`` on the
    LIDAR view ``see`` (braking's ``brake_decision``, or an actor's)."""
    return ShiftPolicy.on_view(space, decide, decisions, interval, LidarView(see), name)


def label_settings(cfg, typed) -> dict:
    """What round 0's labels depend on: the shifts and decisions, the LIDAR view, the training distribution and the
    env (not the training seed)."""
    from ...config import section

    a = typed.agent
    return {
        **a.counterfactual.label_settings(typed.env.step_s),
        "family": "kim",
        "reward": REWARD,
        "lidar": [a.lidar_scans, a.lidar_rays, a.use_speed],
        "impact_offset_spread": a.kim.impact_offset_spread,
        "env": section(cfg, "env"),
    }


def labels_dir(cfg, typed, round_: int, run_dir: Path) -> Path:
    if round_ > 0:
        return Path(run_dir) / "labels" / f"round{round_}"
    seed = typed.agent.counterfactual.label_seed
    name = f"{artifacts.config_sha256(label_settings(cfg, typed))[:10]}-seed{typed.seed if seed is None else seed}"
    return artifacts.data_dir(cfg) / "kim_counterfactual_labels" / name


def label_shard(cfg, typed, round_: int, first: int, stop: int, decide) -> dict:
    """Episodes ``first`` .. ``stop`` - 1 of round ``round_``, driven by ``decide`` (braking or the actor) and
    labelled at each decision."""
    c = typed.agent.counterfactual
    seed = typed.seed if c.label_seed is None else c.label_seed
    env = family_env(cfg, REWARD)
    twin = env.planning_twin()
    policy = shift_policy(
        c.space(env.step_s), decide, c.decisions, c.interval(env.step_s), observer(cfg, REWARD), "labelling"
    )
    parts = []
    for e in range(first, stop):
        spec = training_scenario(typed, KIM_COUNTERFACTUAL_LABELS, round_, e, seed=seed)
        rng = np.random.default_rng([seed, KIM_COUNTERFACTUAL_LABELS, round_, e, KIM_COUNTERFACTUAL_PROPOSALS])
        parts.append(
            label_episode(env, spec, policy, proposer(rng, c), c.continuations(env.step_s), twin, REWARD, False, None)
        )
    env.close()
    return label_parts(parts, first, KEYS)


def labels(cfg, typed, round_: int, n: int, directory: Path, decide, stop=None) -> dict | None:
    """Round ``round_``'s ``n`` labelled episodes in ``directory``, labelling the shards missing; None when
    ``stop`` was requested before they were all labelled."""
    shard = None if decide is None else (lambda first, last: label_shard(cfg, typed, round_, first, last, decide))
    settings = label_settings(cfg, typed) if round_ == 0 else None
    what = f"kim counterfactual labels (round {round_})"
    return shard_labels(directory, n, shard, KEYS, what, settings, stop)


class LidarLabels:
    """Family kim's labelled rounds as the states the shared rounds (``train_rounds``) fit on: the LIDAR view and
    the decision's index, for the actor and the critic alike. No true-state heads (``aux_weight`` 0): their
    targets are the camera family's."""

    def __init__(self, cfg, typed, run_dir):
        self.cfg, self.typed, self.run_dir = cfg, typed, run_dir
        c = typed.agent.counterfactual
        if c.aux_weight:
            raise StageError("the LIDAR learner has no true state to guess: set agent.counterfactual.aux_weight=0")
        if c.critic_obs != "actor":
            raise StageError("the LIDAR critic reads the actor's view: set agent.counterfactual.critic_obs=actor")
        see = observer(cfg, REWARD)
        self.in_dim = self.critic_in = see.dim + 1
        a, step_s = typed.agent, typed.env.step_s
        self.settings = {
            "learner": "counterfactual",
            "in_dim": self.in_dim,
            "critic_in_dim": self.critic_in,
            "critic_obs": "lidar",
            "actor_hidden": list(a.ddpg.actor_hidden),
            "decisions": c.decisions,
            "interval": c.interval(step_s),
            "hold_s": [float(h) for h in c.hold_s],
            "step_s": float(step_s),
            "obs_dim": see.dim,
            "obs": "lidar",
            "lidar_scans": a.lidar_scans,
            "lidar_rays": a.lidar_rays,
            "lidar_speed": a.use_speed,
        }

    def round_data(self, round_: int, n: int, driver: dict | None, stop) -> dict | None:
        decisions = self.typed.agent.counterfactual.decisions
        decide = brake_decision if driver is None else actor_decision(actor_from_state(driver), decisions)
        if driver is None and round_ > 0:
            decide = None  # only reads what an earlier actor of this run labelled
        directory = labels_dir(self.cfg, self.typed, round_, self.run_dir)
        data = labels(self.cfg, self.typed, round_, n, directory, decide, stop)
        if data is None:
            return None
        d = np.concatenate([np.arange(k) for k in np.unique(data["episode"], return_counts=True)[1]])
        data["x"] = data["xc"] = features(data["view"], d, decisions)
        data["state"] = np.zeros((len(d), PRIVILEGED_DIM), np.float32)
        data["held"] = held_out_rows(data["episode"])
        return data


def train(cfg, run_, agent_id) -> dict:
    """``train_agent agent=counterfactual_kim``: the shared rounds on the LIDAR view's labelled states."""
    from ...config import validate

    typed = validate(cfg)
    if agent_id.reward != REWARD:
        raise StageError(f"the counterfactual LIDAR learner learns the {REWARD} cost: train it with reward={REWARD}")
    set_threads(typed.threads)
    seed_everything(typed.seed)  # the checkpoint saves the process-wide generators' state: make it the seed's
    return train_rounds(typed, run_, agent_id.reward, LidarLabels(cfg, typed, run_.dir))


def policy(state: dict, name: str) -> ShiftPolicy:
    """A trained checkpoint as a policy of the evaluation's interface, on the view it was trained with."""
    from envs.counterfactual import ShiftSpace

    see = LidarObserver(False, int(state["lidar_scans"]), int(state["lidar_rays"]), bool(state["lidar_speed"]))
    decisions = int(state["decisions"])
    space = ShiftSpace(tuple(state["hold_s"]), float(state["step_s"]))
    decide = actor_decision(actor_from_state(state), decisions)
    return shift_policy(space, decide, decisions, int(state["interval"]), see, name)
