"""Each scenario family's config sections in the schema, ``agent.<section>`` and ``evaluate.<section>``, as the
families declare them (``Family.agent_config`` and ``Family.eval_config``, written in
worldmodel/families/<name>/config.py).

The schema is built from the registry when the config is imported, so Hydra knows every key when it composes, and
no module of the config names a family."""

from __future__ import annotations

import dataclasses

from .. import registry


def with_family_sections(base: type, schema_of: str, name: str) -> type:
    """``base`` (a config dataclass) with one field more per declared family whose ``Family.<schema_of>`` is a
    section's dataclass: named as the family's section, at that dataclass's defaults.

    The class is called ``name`` in ``base``'s module, which binds that name to it: configs cross into worker
    processes pickled, and pickle finds a class by its module and name."""
    sections = [(f.section, getattr(f, schema_of)) for f in registry.families() if getattr(f, schema_of)]
    built = dataclasses.make_dataclass(
        name,
        [(section, schema, dataclasses.field(default_factory=schema)) for section, schema in sections],
        bases=(base,),
        namespace={"__doc__": base.__doc__},
    )
    built.__module__ = base.__module__
    return built
