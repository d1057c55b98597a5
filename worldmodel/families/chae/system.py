"""Chae et al. 2017 on our simulator: DQN braking with a trauma memory, trained and evaluated on family ``chae``.

    python -m worldmodel.train_agent experiment=NAME agent=dqn_chae [seed=K] [obs=worldmodel]
    python -m worldmodel.evaluate experiment=NAME evaluate.family=chae

Training (``train_agent`` with ``agent.learner=dqn``): ``agent.chae.episodes`` episodes drawn from the paper's
distribution (``envs.chae.sample_chae``: Scenario 1 or 2, TTC ~ U(1.5, 4) s, 10-60 km/h), 0.1 s steps, Chae's four
brake levels and reward Eq. 8; ``worldmodel/models/dqn.py`` learns from one update per step. A transition into a
bump is a trauma. The observation is Chae's 15-value pedestrian history (``agent.obs=pedestrian_history``, the paper's,
privileged: it reads the simulator as their perception module would deliver it) or our world model's
[z, zhat, speed] from the camera (``obs=worldmodel``). Runs: ``runs/NAME/agent_chae_dqn_chae[-worldmodel]/seedK/``
with ``last.pt`` (network, optimiser, both memories, RNG, episode) every ``checkpoint_every_episodes``, TensorBoard
(return, bump rate, ends, loss, epsilon) and ``metrics.json`` with the learning curve.

Evaluation (``evaluate.family=chae``): Table I's layout, Scenario-1 bump rate at each TTC of ``evaluate.chae.ttcs``
over ``evaluate.chae.trials`` seeded trials (the same scenarios for every policy), Scenario 2's unnecessary stops,
the stopping distance to the pedestrian (their Fig. 7), and, since "bump" is only Chae's proxy, footprint contact,
impact speed and Rosen pedestrian injury. Policies: straight-line braking from the pedestrian's start, TTC-threshold
braking, the privileged latest-safe braking, a hand-written closing-speed rule on the agent's own noisy state
(``closing_braking``, not privileged; ``evaluate.chae.policies`` picks among these four), every dqn agent of the
variant. Writes ``runs/NAME/eval_chae/``.

The package, by job: ``observe`` (what the agent sees, the family's env), ``train`` (the trainer), ``select``
(checkpoint selection: validation, rescoring), ``policies`` (scripted rules, trained agents and their ensembles),
``evaluate`` (the bank, the evaluation, the NCAP policies) and ``report`` (summary, tables, figures). Everything
the rest of the repository uses is importable from ``worldmodel.families.chae``.
"""

from __future__ import annotations

from envs.chae import ClosingSpeedBraking, LatestSafeBraking  # noqa: F401

from ..common import DQNPolicy  # noqa: F401
from .evaluate import COLUMNS, bank, evaluate, ncap_policies, run_policy  # noqa: F401
from .observe import (  # noqa: F401
    FAMILY,
    HISTORY_SCALE,
    NCAP_REWARD,
    PRESET,
    HistoryObserver,
    WorldModelObserver,
    family_env,
    observer,
)
from .policies import (  # noqa: F401
    SCRIPTED,
    QEnsemble,
    StraightBraking,
    TTCBraking,
    ensembles,
    load_policy,
    policy_from_state,
)
from .report import (  # noqa: F401
    BAR_BUMP,
    BAR_FROM_TTC,
    BAR_STOPS,
    PAPER_TABLE_I,
    PHYSICS_BAND,
    ROLLING,
    bars_per_run,
    figures,
    learning_curves,
    render_tables,
    summarise,
    tables,
)
from .select import (  # noqa: F401
    Validation,
    member_found,
    rescore_choice,
    rescore_kept,
    rescore_shortlist,
    room,
    selected,
    validated_path,
)
from .train import CHECKPOINT_EPISODES, bumped, episode_scenario, first_target, summary, train  # noqa: F401


def ncap_group(cfg, takeover_ttc_s: float) -> tuple:
    """When to brake is its job: from the test's start, at Chae's 0.1 s steps."""
    return 0.1, ncap_policies(cfg), NCAP_REWARD, None
