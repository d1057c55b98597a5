"""The scenario families the pipeline knows, each declared by its own package under ``worldmodel/families/``.

Shared code (the pipeline, ``train_agent``, ``evaluate``, ``ncap``, ``artifacts``, ``banks``, the config) never names
a family: it reads the declarations here. A declaration (:class:`Family`) is plain data, so reading it imports
nothing heavy; what a family runs (its trainer, evaluation, policies and tables: :class:`System`) is the module
``Family.system`` names, imported on first use. docs/design.md, "How to add a scenario family", walks through it.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Protocol, runtime_checkable

# One line per family, the paper's first (its family is the default wherever none is named): the package that
# declares it as ``FAMILY``. Order matters only where noted in ``Family``.
DECLARED = (
    "worldmodel.families.porav",
    "worldmodel.families.chae",
    "worldmodel.families.kim",
    "worldmodel.families.merola",
)


@dataclasses.dataclass(frozen=True)
class Family:
    """What the shared code needs to know of one scenario family.

    Its env module is ``envs/<name>.py`` (registered in ``envs/families.py``), except the paper's own."""

    name: str
    system: str  # the module implementing System, imported when the family trains, evaluates or reports
    rewards: tuple[str, ...]  # the rewards defined on the family: an agent's reward names the family it belongs to
    # the validation draws of its bank, the default first; every seed that ever judged a configuration stays here
    validation_seeds: tuple[int, ...]
    sealed_seed: int  # its sealed test bank: for final numbers only, drawn at random once, never used to choose
    suite_test_seed: int  # what the test suite's "test bank" is drawn from instead (a seed that judged nothing)
    preset: str | None = None  # its paper's agent preset (conf/agent/), what ``peers=[name]`` trains; None: none
    # the name of the family's config sections ``agent.<section>`` and ``evaluate.<section>``; None: it has none
    section: str | None = None
    # their schemas: config dataclasses (``common.Checked``, in the family's ``config.py``), joined into the schema
    # when the config is imported; None: that section is not there. An agent section may add ``agent_problems(agent)``,
    # its checks against the agent's other keys
    agent_config: type | None = None
    eval_config: type | None = None
    eval_dir: str = ""  # the evaluation folder under runs/NAME/ (``eval_<name>`` when empty)
    # the config key that chooses its validation draw (``evaluate.<section>.seed`` when empty; a family without a
    # section always draws its first validation seed)
    validation_seed_key: str = ""
    # which agents its own trainer runs (``System.train``): those with one of these learners or observations; any
    # other agent on the family trains in train_agent's loop on the world model
    learners: tuple[str, ...] = ()
    observations: tuple[str, ...] = ()
    ensemble_key: str | None = None  # a config key: its agents are judged as ensembles of that many seeds
    selects_checkpoints: bool = False  # its learners choose best.pt on a validation draw (``agent.select``)
    # How the runs recorded so far hashed this family's keys (worldmodel/config/recorded.py applies these):
    # agent.<section>.<key> -> the flat agent key it was before the section existed. A flat key two families moved
    # into one old name is that of the family whose observations the agent has, else of the first declared.
    hashed_as: dict[str, str] = dataclasses.field(default_factory=dict)
    # flat agent keys at the values that meant what their absence meant: left out of the hash
    hashed_defaults: dict[str, object] = dataclasses.field(default_factory=dict)
    # evaluate.<section> keys removed since runs were recorded, with the one value they had: put back before hashing
    removed_eval_keys: dict[str, object] = dataclasses.field(default_factory=dict)

    @property
    def folder(self) -> str:
        return self.eval_dir or f"eval_{self.name}"

    def validation_seed(self, cfg) -> int:
        """The validation draw ``cfg`` chooses for this family."""
        from omegaconf import OmegaConf

        key = self.validation_seed_key or (f"evaluate.{self.section}.seed" if self.section else "")
        return int(OmegaConf.select(cfg, key)) if key else self.validation_seeds[0]

    def trains(self, learner: str, obs: str) -> bool:
        """Whether the family's own trainer runs an agent with this learner and observation."""
        return learner in self.learners or obs in self.observations


@runtime_checkable
class System(Protocol):
    """What a family runs: the module ``Family.system`` names provides these, and ``Trainer``'s too where the family
    declares learners or observations of its own."""

    # the Euro NCAP group: (step_s, [(policy, training seed, sees the camera, runs the car-to-car tests)], the
    # reward its env reports, the TTC at which the policy takes over or None for from the start)
    def ncap_group(self, cfg, takeover_ttc_s: float) -> tuple: ...

    def evaluate(self, cfg) -> dict: ...  # ``evaluate.family=<name>``: its bank, rows, summary and report

    def render_tables(self, rows: list[dict], settings: dict) -> str: ...  # its tables from committed rows


@runtime_checkable
class Trainer(Protocol):
    """A family's own trainer, for the agents ``Family.trains`` picks."""

    def train(self, cfg, run_, agent_id) -> dict: ...  # inside train_agent's TrainingRun; returns its metrics

    def summary(self, metrics: dict) -> str: ...  # the line the log shows after training


_REGISTRY: dict[str, Family] = {}


def register(family: Family) -> Family:
    """Add ``family`` after the declared ones (a name registered already is replaced). The schema was built from
    the declared families, so a family with config sections is declared in ``DECLARED`` instead."""
    if family.agent_config or family.eval_config:
        raise ValueError(
            f"family {family.name!r} declares config sections, which the schema takes from the families in "
            "worldmodel/registry.py's DECLARED when the config is imported: add its package there instead"
        )
    _load()[family.name] = family
    return family


def unregister(name: str) -> None:
    """Remove family ``name`` (a test's own family, once the test is done)."""
    _load().pop(name, None)


def _load() -> dict[str, Family]:
    if not _REGISTRY:
        for module in DECLARED:
            family = importlib.import_module(module).FAMILY
            _REGISTRY[family.name] = family
    return _REGISTRY


def families() -> tuple[Family, ...]:
    """Every registered family, the paper's first."""
    return tuple(_load().values())


def names() -> tuple[str, ...]:
    return tuple(_load())


def default() -> Family:
    """The paper's family: where no family is named."""
    return families()[0]


def family(name: str) -> Family:
    known = _load()
    if name not in known:
        raise KeyError(f"unknown scenario family {name!r}: known are {', '.join(known)}")
    return known[name]


def of_reward(reward: str) -> Family:
    """The family an agent with ``reward`` belongs to (the default family when no family declares it)."""
    return next((f for f in families() if reward in f.rewards), default())


def peers() -> dict[str, str]:
    """Family -> its paper's agent preset, for every family but the default: what ``peers=[...]`` may name."""
    return {f.name: f.preset for f in families()[1:] if f.preset}


def sections() -> tuple[str, ...]:
    """The families' own config sections (``agent.<s>``, ``evaluate.<s>``)."""
    return tuple(f.section for f in families() if f.section)


def system(name: str) -> System:
    """What family ``name`` runs (imported on first use: each pulls in its own models)."""
    return importlib.import_module(family(name).system)


# ----------------------------------------------------------------------------- learners
@dataclasses.dataclass(frozen=True)
class Learner:
    """What the shared code needs to know of one learner (``agent.learner``)."""

    name: str
    sees: tuple[str, ...]  # the observations (``agent.obs``) it can act from
    # the module implementing Trainer: ``run(cfg, agent_id) -> metrics`` trains one agent inside its own TrainingRun,
    # and ``build_policy(name, encoder, state, device)`` rebuilds it from its checkpoint for the evaluations; empty
    # for a learner only families train (their ``system.train`` and evaluations)
    module: str = ""
    # agent keys that only this learner reads: left out of every other learner's config hash
    own_keys: tuple[str, ...] = ()


@runtime_checkable
class LearnerModule(Protocol):
    def run(self, cfg, agent_id) -> dict: ...

    def build_policy(self, name: str, encoder, state: dict, device="cpu"): ...


# One entry per learner, in the order errors list them.
LEARNERS: dict[str, Learner] = {
    learner.name: learner
    for learner in (
        Learner("ddpg", ("worldmodel", "lidar", "privileged"), "worldmodel.learners.ddpg"),
        Learner("chooser", ("worldmodel",), "worldmodel.chooser"),
        # a family's: Chae's and Merola's DQN (worldmodel/families/chae/, merola/), on their own views
        Learner(
            "dqn",
            ("worldmodel", "pedestrian_history", "frames_vae", "frames_resnet", "privileged"),
            own_keys=("dqn", "episodes"),
        ),
        Learner("kim_chooser", ("lidar",), own_keys=("kim_chooser",)),  # family kim's (worldmodel/families/kim/)
        # on family kim also the LIDAR (agent=counterfactual_kim), on family merola Merola's frames
        # (agent=counterfactual_merola): those the families train (families/kim/, merola/)
        Learner(
            "counterfactual",
            ("worldmodel", "privileged", "lidar", "frames_vae"),
            "worldmodel.counterfactual",
            ("counterfactual",),
        ),
    )
}


def register_learner(learner: Learner) -> Learner:
    """Add ``learner`` (a name registered already is replaced)."""
    LEARNERS[learner.name] = learner
    return learner


def unregister_learner(name: str) -> None:
    """Remove learner ``name`` (a test's own learner, once the test is done)."""
    LEARNERS.pop(name, None)


def learner(name: str) -> Learner:
    if name not in LEARNERS:
        raise KeyError(f"unknown learner {name!r}: known are {', '.join(LEARNERS)}")
    return LEARNERS[name]


def learner_module(name: str) -> LearnerModule:
    """What learner ``name`` runs (imported on first use)."""
    module = learner(name).module
    if not module:
        raise KeyError(f"learner {name!r} is trained and evaluated by its scenario family, not on its own")
    return importlib.import_module(module)
