"""The peer systems brought onto our simulator and yardstick (docs/design.md §10), each a module of this package
behind one interface, :class:`Peer`, and found through :data:`REGISTRY`. Peers never import one another; what they
share is in ``peers/common.py``.

A peer declares:

* its scenario family (``FAMILY``, one of ``envs.env.FAMILIES``) and its agent preset (``PRESET``,
  ``conf/agent/<PRESET>.yaml``, which also picks the observation its paper gives it);
* its trainer: ``train(cfg, run_, agent_id) -> metrics``, called by ``train_agent`` inside a ``TrainingRun``, and
  ``summary(metrics)``, the line the log shows;
* its policies: ``load_policy(cfg, agent_id)`` for a trained agent, and ``ncap_policies(cfg)``, what it runs on the
  Euro NCAP bank, as (policy, training seed, sees the camera, runs the car-to-car tests), with ``NCAP_REWARD``;
* its evaluation and report: ``evaluate(cfg)`` on its own family (``evaluate.family=FAMILY``), and
  ``render_tables(rows, settings)``, its tables from its per-scenario rows and the settings its summary records.
"""

from __future__ import annotations

import importlib
from typing import Protocol, runtime_checkable

# family -> the agent preset of its paper (conf/agent/<preset>.yaml); the module or package is worldmodel/peers/<family>
REGISTRY: dict[str, str] = {"chae": "dqn_chae", "kim": "ddpg_kim", "merola": "ddqn_merola"}


@runtime_checkable
class Peer(Protocol):
    FAMILY: str
    PRESET: str
    NCAP_REWARD: str

    def train(self, cfg, run_, agent_id) -> dict: ...

    def summary(self, metrics: dict) -> str: ...

    def load_policy(self, cfg, agent_id): ...

    def ncap_policies(self, cfg) -> list[tuple]: ...

    def evaluate(self, cfg) -> dict: ...

    def render_tables(self, rows: list[dict], settings: dict) -> str: ...


def peer(family: str) -> Peer:
    """The peer system of ``family`` (imported on first use: each pulls in its own models)."""
    if family not in REGISTRY:
        raise KeyError(f"no peer system for family {family!r}: known are {', '.join(REGISTRY)}")
    return importlib.import_module(f"{__name__}.{family}")
