"""Empirical injury-risk models used by reward R2 and by every evaluation metric.

Both are the models the paper uses (Porav & Newman 2018, Eq. 2, 3 and 8):

* pedestrians: Rosen & Sander (2009), fitted to 2127 GIDAS pedestrians,
  P = 1 / (1 + exp(6.9 - 0.09 v)) with v the car's impact speed in km/h;
* car occupants: Joksch (1993), frontal-impact severe-injury risk,
  P = min(1, (dv_mph / 71) ** 4) with dv the occupant's velocity change, 0.621 mph per km/h.
"""

from __future__ import annotations

import math

MS_TO_KMH = 3.6
KMH_TO_MPH = 0.621


def pedestrian_injury(impact_speed_ms: float) -> float:
    """Rosen & Sander risk for a pedestrian struck at ``impact_speed_ms`` (m/s)."""
    v_kmh = abs(impact_speed_ms) * MS_TO_KMH
    return 1.0 / (1.0 + math.exp(6.9 - 0.09 * v_kmh))


def occupant_injury(delta_v_ms: float) -> float:
    """Joksch risk for an occupant whose car changes velocity by ``delta_v_ms`` (m/s); clamped at 1."""
    dv_mph = abs(delta_v_ms) * MS_TO_KMH * KMH_TO_MPH
    return min(1.0, (dv_mph / 71.0) ** 4)


def plastic_delta_v(m_ego: float, m_other: float, relative_speed: float) -> tuple[float, float]:
    """Velocity changes of both cars in a perfectly plastic collision (momentum conservation).

    Both cars end with the common velocity, so each one's change is the other's share of the mass times the
    closing speed: dv_ego = m_other / (m_ego + m_other) * |v_ego - v_other|, and symmetrically.
    """
    total = m_ego + m_other
    return m_other / total * relative_speed, m_ego / total * relative_speed
