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


# Sobhani et al. 2011 (Kim et al. 2020, Eq. 11 and Table 1): ISS = exp(2.011e-7 * 0.5 * M * dV^2 + alpha[side])
SOBHANI_ALPHA = {"near": 2.698, "far": 2.038, "rear": 1.991, "front": 1.991}  # front: Kim's frontal hits, as rear
SOBHANI_ENERGY_COEF = 2.011e-7
ISS_UNITS = ("kmh", "ms")


def injury_severity_score(delta_v_ms: float, side: str, mass_kg: float = 1500.0, units: str = "kmh") -> float:
    """Sobhani's Injury Severity Score for an occupant whose car changes velocity by ``delta_v_ms`` (m/s) when hit
    on ``side`` (near, far, rear or front). The paper does not state ΔV's units: ``units="kmh"`` (default) puts ΔV
    in km/h into the energy term, ``"ms"`` in m/s. With m/s one crash scores at least e^alpha = 7.3-14.9 even at
    ΔV -> 0, which the paper's averages cannot hold; both are reported."""
    if side not in SOBHANI_ALPHA:
        raise ValueError(f"side {side!r}: use one of {', '.join(SOBHANI_ALPHA)}")
    if units not in ISS_UNITS:
        raise ValueError(f"units {units!r}: use one of {', '.join(ISS_UNITS)}")
    dv = abs(delta_v_ms) * (MS_TO_KMH if units == "kmh" else 1.0)
    return math.exp(SOBHANI_ENERGY_COEF * 0.5 * mass_kg * dv * dv + SOBHANI_ALPHA[side])


def damaged_side(local_x: float, local_y: float, half_length: float, half_width: float) -> str:
    """Which side of a car a contact point (in the car's frame: x forward, y to the left) lies on: front or rear
    if it is nearer the car's ends than its flanks (relative to the half-extents), else near (left, the driver's
    side) or far (right), as Kim et al. read Sobhani's sides."""
    if abs(local_x) / half_length >= abs(local_y) / half_width:
        return "front" if local_x > 0 else "rear"
    return "near" if local_y > 0 else "far"
