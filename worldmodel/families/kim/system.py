"""Kim et al. 2020 on our simulator: DDPG with a LIDAR front end against red-light runners, on family ``kim``.

    python -m worldmodel.train_agent experiment=NAME agent=ddpg_kim [reward=kim_aware] [seed=K]
    python -m worldmodel.train_agent experiment=NAME agent=ddpg_wm_kim [seed=K]     # the camera agent
    python -m worldmodel.train_agent experiment=NAME agent=kim_chooser [seed=K]     # the LIDAR chooser
    python -m worldmodel.evaluate experiment=NAME evaluate.family=kim

Training (``train_agent`` with ``agent.obs=lidar``): ``agent.kim.total_steps`` steps of family ``kim``
(envs/kim.py: the three scenarios, lanes and neutral cars drawn uniformly, the ego at U(10, 50) km/h), 0.1 s steps;
the existing DDPG (worldmodel/models/ddpg.py) with Kim's 1-D convolutions over the LIDAR's angle
(``agent.lidar_scans``). The observation is the last 4 scans of the 36-ray LIDAR and the previous action
(envs/lidar.py); with the goal-aware reward ``kim_aware`` (Eq. 10) also the distance and angle to the goal, as in the
paper. The action is (desired speed, steering angle), mapped onto our controls by ``envs.kim.kim_action``. Runs:
``runs/NAME/agent_kim_unaware_ddpg_kim/seedK/`` (and ``agent_kim_aware_ddpg_kim``), resumable, with TensorBoard
(return, rolling avoidance) and ``metrics.json`` with the learning curve.

The LIDAR chooser (``agent=kim_chooser``, ``chooser``) is no DDPG: it brakes and switches once to the manoeuvre
whose cost an MLP predicts lowest from the LIDAR view, learnt from exact costs re-simulated on braking's states.

Evaluation (``evaluate.family=kim``): Table 2's layout, avoidance % (no collision of any kind in the episode) and
mean injury (minus the summed Sobhani ISS, as the paper's table gives it) per scenario and overall, for every
LIDAR agent (the chooser among them), every world-model agent trained on the family (``agent=ddpg_wm_kim``: camera
frames, at the world model's 1/15 s steps), the paper's street-trained agents as they are
(``evaluate.kim.world_model_agents``), AEB-3m, straight-line braking and the privileged planner, on
``evaluate.kim.trials`` seeded trials per scenario (the first ``paper_trials`` of them make the paper-sized table),
with 95 % Wilson intervals and pairwise paired permutation tests on per-trial injury. Writes ``runs/NAME/eval_kim/``.

The modules: ``observe`` (the LIDAR observer, the family's env and its training scenarios), ``teach`` (the planner
as teacher: demonstrations, cloning, DAgger), ``trainer`` (``train``, ``summary``, the trained LIDAR policy),
``chooser`` (the LIDAR chooser's labels, scorer and policy; imported when used, as it needs torch), ``evaluation``
(the trial bank, ``run_policy``, ``evaluate``, the NCAP policies) and ``report`` (the summary, Table 2's tables
and the figure).
"""

from .evaluation import COLUMNS, bank, draw_suffix, evaluate, ncap_policies, run_policy, scripted
from .observe import (
    FAMILY,
    GOAL_REWARDS,
    NCAP_REWARD,
    PRESET,
    LidarObserver,
    ddpg_config,
    family_env,
    observer,
    training_scenario,
)
from .report import PAPER_TABLE_2, figure, render_tables, summarise, tables
from .teach import HELD_OUT_SHARE, STEERING_LABEL, dagger_labels, learn_from_planner, planner_demonstrations, teacher
from .trainer import CHECKPOINT_EPISODES, ROLLING, LidarPolicy, load_policy, summary, train

__all__ = [
    "CHECKPOINT_EPISODES",
    "COLUMNS",
    "FAMILY",
    "GOAL_REWARDS",
    "HELD_OUT_SHARE",
    "NCAP_REWARD",
    "PAPER_TABLE_2",
    "PRESET",
    "ROLLING",
    "STEERING_LABEL",
    "LidarObserver",
    "LidarPolicy",
    "bank",
    "dagger_labels",
    "ddpg_config",
    "draw_suffix",
    "evaluate",
    "family_env",
    "figure",
    "learn_from_planner",
    "load_policy",
    "ncap_policies",
    "observer",
    "planner_demonstrations",
    "render_tables",
    "run_policy",
    "scripted",
    "summarise",
    "summary",
    "tables",
    "teacher",
    "training_scenario",
    "train",
]


def ncap_group(cfg, takeover_ttc_s: float) -> tuple:
    """Its agents drive from the test's start, at Kim's 0.1 s steps."""
    return 0.1, ncap_policies(cfg), NCAP_REWARD, None
