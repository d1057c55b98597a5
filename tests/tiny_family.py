"""A scenario family that exists only in the tests, added by the steps of docs/design.md §11 ("How to add a scenario
family") and nothing else: the car ahead stands still in the ego's lane, ``ttc`` seconds away at the ego's speed.

Everything the family needs is in this file: its scenarios (what ``envs/<name>.py`` holds for a real family), its
reward, its declaration (a real family's ``worldmodel/families/<name>/__init__.py``), what it runs (its
``system.py``) and its agent preset (a real family's ``conf/agent/<preset>.yaml``). ``registered()`` is the one line
per registry that a real family adds to ``envs/families.py``, ``envs/rewards.py``, ``worldmodel/registry.py`` and
``conf/agent/``, undone when the test is over.
"""

from __future__ import annotations

import contextlib
import csv
import json
from dataclasses import dataclass

import numpy as np
from hydra.core.config_store import ConfigStore

from envs import families as env_families
from envs import rewards
from envs.actors import Actors
from envs.scene import EGO_LANE_Y
from envs.specs import FamilySpec
from worldmodel import registry

NAME = "tiny"
CAR_LENGTH = 4.5


# ----------------------------------------------------------------------------- the scenarios (envs/<name>.py)
@dataclass(frozen=True)
class TinySpec(FamilySpec):
    """A car standing in the ego's lane; the ego at ``ego_speed`` m/s reaches it in ``ttc`` s."""

    seed: int
    ego_speed: float
    ttc: float
    family: str = NAME

    @property
    def hazard(self) -> str:
        return "car"


@dataclass
class TinyState:
    """Nothing moves but the ego; an episode ends at a stop, a crash or after ``horizon_s``."""

    horizon_s: float = 3.0

    def substep(self, actors, bumper_before, bumper_after, t0, tau, sub_dt) -> None:
        pass

    def context(self, actors, bumper_x, ego=None) -> dict:
        return {}

    def end(self, actors, bumper_x, speed, ctx, ego=None) -> str | None:
        return "stopped" if speed < 0.1 else None

    def outcome(self, spec, bumper_x) -> dict:
        return {"family": NAME}


def sample(rng: np.random.Generator) -> TinySpec:
    return TinySpec(int(rng.integers(0, 2**31 - 1)), float(rng.uniform(8.0, 14.0)), float(rng.uniform(0.8, 1.5)))


def build(spec: TinySpec, ego_front: float) -> tuple[Actors, TinyState]:
    actors = Actors.empty(collision_point=None)
    actors.car_xy[0] = (ego_front + spec.ego_speed * spec.ttc + CAR_LENGTH / 2, EGO_LANE_Y)
    actors.car_active[0] = actors.car_hazard[0] = True
    return actors, TinyState()


class Scenarios:  # the module interface envs/families.py registers: FAMILY, SPEC, sample, build
    FAMILY, SPEC = NAME, TinySpec
    sample, build = staticmethod(sample), staticmethod(build)


# ----------------------------------------------------------------------------- its reward (envs/rewards.py)
def reward(ctx: rewards.StepContext) -> float:
    """Minus the summed injury risk of the step's collisions."""
    return -float(sum(hit["injury_sum"] for hit in ctx.hits))


# ----------------------------------------------------------------------------- its declaration
FAMILY = registry.Family(
    name=NAME,
    system=__name__,  # this module: evaluate, ncap_group and render_tables below
    rewards=(NAME,),
    validation_seeds=(5,),
    sealed_seed=90001,
    suite_test_seed=90002,
    preset="ddpg_tiny",
)
# its preset: the paper's DDPG on the world model (train_agent's own loop: the family declares no learner)
PRESET = {
    "env": {"family": NAME},
    "reward": {"name": NAME},
    "agent": {"variant": "ddpg_tiny", "learner": "ddpg", "rewards": [NAME]},
}


# ----------------------------------------------------------------------------- what it runs (its system.py)
NCAP_REWARD = NAME
COLUMNS = ("policy", "policy_seed", "scenario_seed", "ttc", "vehicle_collision", "speed_at_collision", "end")


def bank(seed: int) -> list[TinySpec]:
    return [sample(np.random.default_rng([seed, k])) for k in range(3)]


def evaluate(cfg) -> dict:
    """Braking and every agent trained on the family, on the same scenarios; rows, tables, summary, provenance."""
    from envs import StraightLineBraking, rollout
    from worldmodel import artifacts, banks, policies
    from worldmodel.common import make_env

    out = artifacts.eval_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    record = artifacts.provenance(cfg, "eval")
    specs = bank(banks.draw_seed(cfg.evaluate.bank, NAME, FAMILY.validation_seed(cfg)))
    acting = [("braking", StraightLineBraking(), 0)]
    for agent in artifacts.trained_agents(cfg, NAME):
        policy, seed, _ = policies.learned_policy(cfg, agent)
        acting.append((agent.key.partition("/")[0], policy, seed))
    env = make_env(cfg)
    rows = []
    for name, policy, seed in acting:
        for spec in specs:
            o = rollout(env, policy, spec).outcome
            rows.append({"policy": name, "policy_seed": seed, "scenario_seed": spec.seed, "ttc": spec.ttc} | o)
    env.close()
    with open(out / "results.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (out / "tables.md").write_text(render_tables(rows, {}))
    artifacts.write_provenance(out, record)
    summary = {"family": NAME, "policies": sorted({r["policy"] for r in rows}), "scenarios": len(specs)}
    (out / "summary.json").write_text(json.dumps(summary))  # last: it marks the evaluation complete
    return summary


def ncap_group(cfg, takeover_ttc_s: float) -> tuple:
    return 0.1, [], NCAP_REWARD, None  # no policy of its own on the Euro NCAP bank


def render_tables(rows: list[dict], settings: dict) -> str:
    lines = ["| policy | collisions |", "|---|---|"]
    for policy in sorted({r["policy"] for r in rows}):
        mine = [r for r in rows if r["policy"] == policy]
        lines.append(f"| {policy} | {sum(int(r['vehicle_collision']) for r in mine)} of {len(mine)} |")
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def registered():
    """The family's one line in each registry, taken back afterwards."""
    env_families.register(Scenarios)
    rewards.register(NAME, "minus the injury risk of the step's collisions")(reward)
    registry.register(FAMILY)
    ConfigStore.instance().store(group="agent", name=FAMILY.preset, node=PRESET, package="_global_")
    try:
        yield FAMILY
    finally:
        ConfigStore.instance().repo["agent"].pop(f"{FAMILY.preset}.yaml", None)
        registry.unregister(NAME)
        rewards.unregister(NAME)
        env_families.unregister(NAME)
