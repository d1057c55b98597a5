"""Rewards R1 and R2 (Porav & Newman 2018, Eq. 7 and 8), given on the step a collision happens.

R1 = -(n_ped + n_occ) counts the people involved; R2 = -(sum P_ped + sum P_occ) weights them by the
empirical injury risks of ``envs.injury``. Otherwise the reward is 0, exactly as in the paper.
"""

from __future__ import annotations

REWARDS = ("r1", "r2")


def collision_rewards(collisions: list[dict]) -> tuple[float, float]:
    """(R1, R2) of the collisions registered in one step."""
    r1 = -float(sum(c["n_involved"] for c in collisions))
    r2 = -float(sum(c["injury_sum"] for c in collisions))
    return r1, r2
