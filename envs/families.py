"""The scenario families the simulator builds, by name: the paper's (``porav``, ``envs/scenario.py``) and one module
per other family, registered here.

A family module has ``FAMILY`` (its name), ``SPEC`` (a frozen, validated spec dataclass whose dict carries
``family``; ``envs.specs.FamilySpec``), ``sample(rng)`` and ``build(spec, ego_front) -> (actors, state)``; the
state's hooks (``substep``, ``context``, ``end``, ``outcome``, ``horizon_s``) drive its episodes. A spec may say
where the ego starts across the road (``ego_y``); a module may bring its own obstacles (``layout(spec, state,
rng)``) instead of the street's, with the bodies and the ground that draw them for the camera.
"""

from __future__ import annotations

from types import ModuleType

from . import chae, kim, merola, ncap
from .scenario import ScenarioSpec

PAPER = "porav"  # the paper's family: ScenarioSpec, sampled by envs.scenario; no module of its own
MODULES: dict[str, ModuleType] = {}


def register(module: ModuleType) -> ModuleType:
    """Add a family module (a name registered already is replaced: a test may register its own)."""
    MODULES[module.FAMILY] = module
    return module


for _module in (chae, ncap, kim, merola):  # one line per family
    register(_module)


def unregister(name: str) -> None:
    """Remove family ``name`` (a test's own family, once the test is done)."""
    MODULES.pop(name, None)


def names() -> tuple[str, ...]:
    """Every family ``UrbanCollisionEnv(family=...)`` can sample, the paper's first."""
    return (PAPER, *MODULES)


def spec_types() -> tuple[type, ...]:
    return (ScenarioSpec, *(m.SPEC for m in MODULES.values()))


def spec_from_dict(d: dict):
    """A scenario spec of any family from its dict (``"family"`` absent: the paper's)."""
    family = d.get("family", PAPER)
    if family == PAPER:
        return ScenarioSpec.from_dict(d)
    if family in MODULES:
        return MODULES[family].SPEC.from_dict(d)
    raise ValueError(f"unknown scenario family {family!r}: known are {', '.join(names())}")
