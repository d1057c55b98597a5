"""The paper's family (Porav & Newman 2018): a car <= 1.5 s from a pedestrian or a car on an urban street, the
world-model agents trained on rewards R1 and R2, judged against straight-line braking and the privileged planner.
Its scenarios are ``envs/scenario.py``; its agents train in ``worldmodel/train_agent.py``'s own loop; its
evaluation and Euro NCAP group are ``system.py``."""

from ...registry import Family

FAMILY = Family(
    name="porav",
    system="worldmodel.families.porav.system",
    rewards=("r1", "r2"),
    # 2018: the bank every result before the sealed banks existed was judged on
    validation_seeds=(4711, 4712, 2018),
    sealed_seed=56171,
    suite_test_seed=61001,
    eval_dir="eval",
    validation_seed_key="evaluate.validation_seed",
)
