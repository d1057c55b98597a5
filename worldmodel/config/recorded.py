"""What a run's config hash covers: a stage's settings in the layout the recorded runs were hashed with.

Options added to a section at their off value, keys removed or moved since a run was recorded, and keys that only
another learner reads are brought back to that layout before hashing (``artifacts.provenance``), so a change of
the config's shape alone never makes a recorded run stale. A change of what a run computes must change its hash.

Each rule is declared beside the keys it covers:

- a config section's own keys by the section (``Checked.UNHASHED``, ``ADDED_OFF``, ``REMOVED`` and
  ``as_recorded``; e.g. ``DQNConfig``, ``ChooserConfig``, ``EvaluateConfig``), which ``as_recorded`` here applies
  to every section of the settings, nested ones first;
- a family's own sections by the family (``Family.hashed_as``, ``hashed_defaults``, ``removed_eval_keys``:
  worldmodel/registry.py);
- the keys only one learner reads by the learner (``Learner.own_keys``).
"""

from __future__ import annotations

import dataclasses
import typing

from .. import registry


def _sections_as_recorded(schema, values: dict, settings: dict) -> None:
    """``values`` (a section of schema ``schema``, a plain dict) and every section inside it as recorded runs
    hashed them, innermost first."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        inner = values.get(f.name)
        if isinstance(inner, dict) and dataclasses.is_dataclass(hints.get(f.name)):
            _sections_as_recorded(hints[f.name], inner, settings)
    if hasattr(schema, "as_recorded"):
        schema.as_recorded(values, settings)


def _legacy_layout(agent) -> None:
    """Each family's section back at the flat agent keys the runs before the sections were hashed with
    (``Family.hashed_as``). A flat key two families moved into one old name (Kim's and Merola's total_steps were
    one key, peer_total_steps) is that of the family whose observations the agent has, else of the first declared."""
    from .agent import AgentConfig

    if not isinstance(agent, dict):
        return
    families = [f for f in registry.families() if f.section]
    sections = {f.section: agent.pop(f.section, None) or {} for f in families}
    obs = agent.get("obs", AgentConfig.ADDED_OFF["obs"])  # left out of the hash at its default
    put = set()
    for f in families:
        own = obs in f.observations
        for key, old in f.hashed_as.items():
            if key in sections[f.section] and (old not in put or own):
                agent[old] = sections[f.section][key]
                put.add(old)


def as_recorded(settings: dict) -> dict:
    """``settings`` (a stage's config sections, plain dicts) as the runs recorded so far hashed them: each
    section's declared rules, then the families' sections back at their old names with their added defaults left
    out and removed keys put back, and the keys of other learners left out."""
    from .experiment import ExperimentConfig

    schema = typing.get_type_hints(ExperimentConfig)
    for name, values in settings.items():
        if isinstance(values, dict) and dataclasses.is_dataclass(schema.get(name)):
            _sections_as_recorded(schema[name], values, settings)
    agent = settings.get("agent")
    _legacy_layout(agent)
    evaluate = settings.get("evaluate")
    for f in registry.families():
        own = evaluate.get(f.section) if isinstance(evaluate, dict) and f.section else None
        if isinstance(own, dict):
            for key, value in f.removed_eval_keys.items():
                own.setdefault(key, value)
    if isinstance(agent, dict):
        for learner in registry.LEARNERS.values():  # keys only one learner reads (Learner.own_keys) shape no other
            if agent.get("learner") != learner.name:
                for key in learner.own_keys:
                    agent.pop(key, None)
        for f in registry.families():
            for key, default in f.hashed_defaults.items():
                if key in agent and agent[key] == default:
                    agent.pop(key)
    return settings


def inputs_as_recorded(recorded: dict, current: dict) -> dict:
    """The input identities a run recorded (``recorded``), against the ``current`` ones: an agent that sees the
    frozen VAE's means of its frames (``obs=frames_vae``, Merola's) recorded no input before the VAE became one, so
    a record without any input is taken as built on the current VAE. Every such run on disk was trained on the VAE
    of its experiment, which nothing rebuilt; from now on the VAE is recorded and a new one makes the agent stale."""
    if not recorded and set(current) == {"vae"}:
        return dict(current)
    return recorded
