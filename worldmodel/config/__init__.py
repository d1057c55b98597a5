"""The configuration: its schema (one dataclass per config section, registered in Hydra's ConfigStore), its
validation, and the two ways in (``compose`` for tests and notebooks, ``hydra_main`` for the stage commands).

The dataclasses are the single source of truth for every key, its type and its default (docs/design.md §9).
``conf/*.yaml`` only choose groups and override values (the ``scale`` presets, the ``reward`` choice), so a
misspelt key or a value of the wrong type stops Hydra at composition, naming the key. What a type cannot say
(a size must be positive, a share must lie in [0, 1]) is checked by one small ``problems()`` per dataclass, next to
its fields; ``validate(cfg)`` runs them all when a stage starts, and an impossible value stops the stage with
a ``StageError`` naming the key, before any work is done.

The schema is split by section: ``data`` (paths, collection, demonstrations, the scene), ``world_model`` (VAE,
LSTM), ``agent`` (every learner and the reward), ``evaluation`` (the banks' sections, the planner, NCAP),
``experiment`` (the whole, registered in Hydra's ConfigStore) and ``entry`` (validation, presets, ``compose``,
``hydra_main``). Everything is importable from ``worldmodel.config``.
"""

from __future__ import annotations

from .agent import (  # noqa: F401
    MASK_CAMERAS,
    OBSERVATIONS,
    AgentConfig,
    AgentSettings,
    ChooserConfig,
    CounterfactualConfig,
    KimChooserConfig,
    RewardConfig,
)
from .data import (  # noqa: F401
    AutopilotConfig,
    BranchConfig,
    CollectConfig,
    DemosConfig,
    EnvConfig,
    FocusConfig,
    PathsConfig,
)
from .entry import (  # noqa: F401
    agent_preset,
    compose,
    hydra_main,
    oracle_settings,
    peer_preset,
    preset_globals,
    section,
    teacher_settings,
    validate,
)
from .evaluation import (  # noqa: F401
    SCRIPTED_POLICIES,
    EvaluateConfig,
    EvaluateSettings,
    NcapConfig,
    OracleConfig,
)
from .experiment import (  # noqa: F401
    ExperimentConfig,
    register,
)
from .world_model import (  # noqa: F401
    RNN_HEADS,
    RNNConfig,
    VAEConfig,
)
