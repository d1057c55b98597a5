"""Properties over generated inputs: scenario specs are accepted exactly inside their documented ranges, the
injury-risk models never fall as the impact gets harder, and every step reward equals its published formula
(constants typed in from the papers, docs/design.md §3 and §10)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs import ScenarioSpec
from envs.injury import occupant_injury, pedestrian_injury
from envs.rewards import REGISTRY, StepContext, chae, kim_aware, kim_unaware, merola, r1, r2, step_rewards

# Fixed examples: the same inputs on every run and machine, and no example database written into the tree.
PROPERTY = settings(max_examples=60, deadline=None, derandomize=True, database=None)

# ----------------------------------------------------------------------------- scenario specs
# (lo, hi] for the continuous fields, as envs/scenario.py documents them
OPEN_CLOSED = {
    "ttc": (0.0, 10.0),
    "ego_speed": (0.0, 40.0),
    "pedestrian_speed": (0.0, 10.0),
    "hazard_car_speed": (0.0, 30.0),
}
MAX_OTHERS = 10


def in_range(lo, hi):
    return st.floats(min_value=lo, max_value=hi, exclude_min=True, allow_nan=False)


valid_specs = st.fixed_dictionaries(
    {
        "seed": st.integers(0, 2**31 - 1),
        **{name: in_range(lo, hi) for name, (lo, hi) in OPEN_CLOSED.items()},
        "n_cars": st.integers(0, MAX_OTHERS),
        "n_pedestrians": st.integers(0, MAX_OTHERS),
        "p_pedestrian": st.floats(0.0, 1.0),
        "p_car": st.floats(0.0, 1.0),
    }
)


def not_integer(lo, hi):
    return st.floats(lo, hi, allow_nan=False).filter(lambda x: x != int(x))


def invalid_values(name: str):
    """Values of one field that a spec must refuse; non-finite counts and seeds have their own test below."""
    if name in OPEN_CLOSED:
        lo, hi = OPEN_CLOSED[name]
        return st.floats(max_value=lo) | st.floats(min_value=hi, exclude_min=True) | st.just(math.nan)
    if name in ("n_cars", "n_pedestrians"):
        outside = st.integers(max_value=-1) | st.integers(min_value=MAX_OTHERS + 1)
        return outside | not_integer(-5.0, MAX_OTHERS + 5.0)
    if name in ("p_pedestrian", "p_car"):
        return (
            st.floats(max_value=0.0, exclude_max=True) | st.floats(min_value=1.0, exclude_min=True) | st.just(math.nan)
        )
    assert name == "seed"
    return st.integers(max_value=-1) | not_integer(0.0, 1e6)


@PROPERTY
@given(valid_specs)
def test_a_spec_inside_every_range_is_accepted_and_round_trips(fields):
    spec = ScenarioSpec(**fields)
    assert ScenarioSpec.from_dict(spec.to_dict()) == spec
    assert spec.pedestrian_hazard == (fields["p_pedestrian"] > 0.5) and spec.car_hazard == (fields["p_car"] > 0.5)


FIELDS = [*OPEN_CLOSED, "n_cars", "n_pedestrians", "p_pedestrian", "p_car", "seed"]
one_bad_field = st.sampled_from(FIELDS).flatmap(lambda name: st.tuples(st.just(name), invalid_values(name)))


@PROPERTY
@given(valid_specs, one_bad_field)
def test_a_spec_with_one_field_out_of_range_is_refused_naming_the_field(fields, bad):
    name, value = bad
    with pytest.raises(ValueError, match=name):
        ScenarioSpec(**{**fields, name: value})


@pytest.mark.parametrize("name", ["seed", "n_cars", "n_pedestrians"])
@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_a_non_finite_count_or_seed_is_refused_naming_the_field(name, value):
    with pytest.raises(ValueError, match=name):
        ScenarioSpec(**{"seed": 1, "ttc": 1.0, "ego_speed": 10.0, name: value})


def test_a_spec_is_written_as_json_with_sorted_keys():
    spec = ScenarioSpec(seed=3, ttc=1.0, ego_speed=10.0, n_cars=2, p_car=1.0)
    text = spec.to_json()
    assert json.loads(text) == spec.to_dict() and list(json.loads(text)) == sorted(spec.to_dict())
    assert ScenarioSpec.from_dict(json.loads(text)) == spec


def test_unknown_fields_are_refused():
    with pytest.raises(ValueError, match="speed_kmh"):
        ScenarioSpec.from_dict({"seed": 1, "ttc": 1.0, "ego_speed": 10.0, "speed_kmh": 36.0})


# ----------------------------------------------------------------------------- injury risks
speeds = st.floats(0.0, 80.0)


@PROPERTY
@given(speeds, speeds)
def test_injury_risk_never_falls_as_the_impact_speed_rises(a, b):
    slow, fast = sorted((a, b))
    for risk in (pedestrian_injury, occupant_injury):
        assert 0.0 <= risk(slow) <= risk(fast) <= 1.0
        assert risk(-fast) == risk(fast)  # a speed's sign (which way the cars moved) does not matter


@PROPERTY
@given(speeds)
def test_injury_risks_are_the_published_curves(v):
    kmh = 3.6 * v
    assert pedestrian_injury(v) == pytest.approx(1.0 / (1.0 + math.exp(6.9 - 0.09 * kmh)), rel=1e-12)
    assert occupant_injury(v) == pytest.approx(min(1.0, (0.621 * kmh / 71.0) ** 4), rel=1e-12)


# ----------------------------------------------------------------------------- step rewards
SOBHANI_ALPHA = {"near": 2.698, "far": 2.038, "rear": 1.991, "front": 1.991}  # Kim et al. 2020, Table 1


@st.composite
def hits(draw):
    """One collision record as the env registers it: a pedestrian struck, or a crash with a car or an obstacle."""
    kind = draw(st.sampled_from(["pedestrian", "vehicle", "static"]))
    speed = draw(st.floats(0.0, 40.0))
    dv = 0.0 if kind == "pedestrian" else draw(st.floats(0.0, 40.0))
    n = 1 if kind == "pedestrian" else draw(st.integers(1, 4))
    return {
        "kind": kind,
        "impact_speed": speed,
        "delta_v_ego": dv,
        "ego_side": "front" if kind == "pedestrian" else draw(st.sampled_from(sorted(SOBHANI_ALPHA))),
        "n_involved": n,
        "injury_sum": draw(st.floats(0.0, float(n))),
    }


@st.composite
def steps(draw):
    family = {}
    if draw(st.booleans()):  # a Chae episode: the pedestrian's distance and whether the bumper passed the line
        family = {"dx": draw(st.floats(0.0, 80.0)), "bump": draw(st.booleans())}
    if draw(st.booleans()):
        family["goal_progress"] = draw(st.floats(-2.0, 2.0))
    return StepContext(
        hits=draw(st.lists(hits(), max_size=3)),
        speed_before=draw(st.floats(0.0, 30.0)),
        speed_after=draw(st.floats(0.0, 30.0)),
        action=np.array([draw(st.floats(-1.0, 1.0)), draw(st.floats(-1.0, 1.0))]),
        step_s=draw(st.sampled_from([1.0 / 15.0, 0.1])),
        family=family,
        heading=draw(st.floats(-math.pi, math.pi)),
    )


def iss(hit) -> float:
    kmh = 3.6 * hit["delta_v_ego"]
    return math.exp(2.011e-7 * 0.5 * 1500.0 * kmh**2 + SOBHANI_ALPHA[hit["ego_side"]])


def merola_by_hand(ctx: StepContext) -> float:
    steer, pedal = ctx.action
    r = 0.5 * (ctx.speed_before + ctx.speed_after) * ctx.step_s
    for h in ctx.hits:
        dv = h["impact_speed"] if h["kind"] == "pedestrian" else h["delta_v_ego"]
        r -= min(100.0, max(1.0, 100.0 * dv / (60.0 / 3.6)))
    if (pedal < 0 and ctx.speed_after < 2.0) or (pedal > 0 and ctx.speed_after > 60.0 / 3.6):
        r -= 5.0
    further_off = (ctx.heading > 0 and steer < 0) or (ctx.heading < 0 and steer > 0)
    if abs(ctx.heading) > math.radians(10.0) and further_off:
        r -= 1.0
    return r


@PROPERTY
@given(steps())
def test_every_step_reward_is_its_formula(ctx):
    crashes = [h for h in ctx.hits if h["kind"] != "pedestrian"]
    assert r1(ctx) == -sum(h["n_involved"] for h in ctx.hits)
    assert r2(ctx) == pytest.approx(-sum(h["injury_sum"] for h in ctx.hits), abs=1e-12)
    assert kim_unaware(ctx) == pytest.approx(-sum(iss(h) for h in crashes), rel=1e-12)
    expected_aware = -sum(iss(h) for h in crashes) if crashes else ctx.family.get("goal_progress", 0.0)
    assert kim_aware(ctx) == pytest.approx(expected_aware, rel=1e-12)
    if "dx" in ctx.family:
        dx, bump, v1 = ctx.family["dx"], ctx.family["bump"], ctx.speed_after
        decel = ctx.speed_before - v1
        expected_chae = -(0.001 * dx**2 + 0.1) * decel - (0.01 * v1**2 + 100.0) * bump
    else:
        expected_chae = 0.0  # another family's step
    assert chae(ctx) == pytest.approx(expected_chae, rel=1e-12, abs=1e-12)
    assert merola(ctx) == pytest.approx(merola_by_hand(ctx), rel=1e-12, abs=1e-12)
    # what the env reports is the same numbers, one per registered reward
    reported = step_rewards(ctx)
    assert set(reported) == set(REGISTRY)
    assert reported["r2"] == r2(ctx) and reported["merola"] == merola(ctx)


# ----------------------------------------------------------------------------- Kim's injury severity score
# Sobhani et al. 2011 as Kim et al. 2020 give it (Eq. 11, Table 1): constants typed in from the papers
SOBHANI = {"near": 2.698, "far": 2.038, "rear": 1.991, "front": 1.991}


@PROPERTY
@given(st.floats(-30.0, 30.0), st.sampled_from(sorted(SOBHANI)), st.floats(800.0, 3000.0))
def test_injury_severity_score_is_sobhanis_formula(dv, side, mass):
    from envs.injury import injury_severity_score

    kmh = abs(dv) * 3.6
    assert injury_severity_score(dv, side, mass) == pytest.approx(
        math.exp(2.011e-7 * 0.5 * mass * kmh**2 + SOBHANI[side])
    )
    assert injury_severity_score(dv, side, mass, units="ms") == pytest.approx(
        math.exp(2.011e-7 * 0.5 * mass * dv**2 + SOBHANI[side])
    )
    # the defaults: a 1500 kg car, delta-v in km/h
    assert injury_severity_score(dv, side) == injury_severity_score(dv, side, 1500.0, "kmh")


def test_injury_severity_score_names_a_bad_side_or_unit():
    from envs.injury import injury_severity_score

    with pytest.raises(ValueError, match=r"side 'top': use one of near, far, rear, front"):
        injury_severity_score(5.0, "top")
    with pytest.raises(ValueError, match=r"units 'mph': use one of kmh, ms"):
        injury_severity_score(5.0, "near", units="mph")


def test_damaged_side_by_the_nearest_end_or_flank():
    from envs.injury import damaged_side

    hl, hw = 2.0, 0.9  # not 1: dividing by the half-width and multiplying by it must differ
    cases = {
        (1.9, 0.2): "front",
        (0.5, 0.2): "front",  # nearer the front than a flank, relative to the half-extents
        (-1.9, -0.2): "rear",
        (0.5, 0.85): "near",  # the left flank
        (-0.5, 0.5): "near",
        (0.5, -0.85): "far",
        (1.0, 0.5): "near",  # half-way along, nearer the flank relative to the half-width
        (1.0, 0.45): "front",  # on the diagonal: an end
        (-1.0, -0.45): "rear",
    }
    for (x, y), side in cases.items():
        assert damaged_side(x, y, hl, hw) == side, (x, y)


# ----------------------------------------------------------------------------- the crash penalties inside rewards
def hit(kind: str, **values) -> dict:
    return {"kind": kind, "n_involved": 1, "injury_sum": 0.0, **values}


def test_kims_crash_iss_sums_car_and_object_crashes_only():
    from envs.injury import injury_severity_score
    from envs.rewards import crash_iss

    hits = [
        hit("pedestrian", delta_v_ego=0.5, ego_side="front", impact_speed=8.0),
        hit("vehicle", delta_v_ego=6.0, ego_side="near"),
        hit("static", delta_v_ego=3.0, ego_side="front"),
    ]
    for units in ("kmh", "ms"):
        expected = injury_severity_score(6.0, "near", units=units) + injury_severity_score(3.0, "front", units=units)
        assert crash_iss(hits, units=units) == pytest.approx(expected)
    assert crash_iss(hits[:1]) == 0.0


def test_merolas_impact_penalty_adds_every_crash_clipped_to_1_100():
    from envs.rewards import merola_impact

    full = 60.0 / 3.6
    assert merola_impact([hit("vehicle", delta_v_ego=full / 2)]) == pytest.approx(50.0)
    assert merola_impact([hit("pedestrian", impact_speed=full / 4, delta_v_ego=0.0)]) == pytest.approx(25.0)
    assert merola_impact([hit("static", delta_v_ego=0.001)]) == 1.0  # a touch still costs 1
    assert merola_impact([hit("vehicle", delta_v_ego=3 * full)]) == 100.0
    two = [hit("vehicle", delta_v_ego=full / 2), hit("pedestrian", impact_speed=full / 4, delta_v_ego=0.0)]
    assert merola_impact(two) == pytest.approx(75.0)


def test_collision_rewards_and_the_registry():
    from envs.rewards import REGISTRY, collision_rewards, register

    hits = [hit("pedestrian", n_involved=1, injury_sum=0.4), hit("vehicle", n_involved=2, injury_sum=0.25)]
    assert collision_rewards(hits) == (-3.0, pytest.approx(-0.65))
    assert collision_rewards([]) == (0.0, 0.0)
    for name, reward in REGISTRY.items():
        assert reward.name == name and reward.doc and callable(reward.fn)
    with pytest.raises(ValueError, match="reward 'r1' is registered twice"):
        register("r1", "again")(lambda ctx: 0.0)


def test_a_reward_registered_while_running_is_listed_and_removed_again():
    """The rewards above are registered when the module is imported; one a test (or a family) adds later gets the
    same entry, joins ``REWARDS`` after them, and ``unregister`` takes it out of both (a second time: nothing)."""
    from envs import rewards

    def nothing(ctx):
        return 0.0

    before = rewards.REWARDS
    assert rewards.register("test_only", "a test's own reward")(nothing) is nothing
    try:
        assert rewards.REGISTRY["test_only"] == rewards.Reward("test_only", nothing, "a test's own reward")
        assert rewards.REWARDS == (*before, "test_only") == tuple(rewards.REGISTRY)
    finally:
        rewards.unregister("test_only")
    assert rewards.REWARDS == before == tuple(rewards.REGISTRY)
    rewards.unregister("test_only")
    assert rewards.REWARDS == before


# ----------------------------------------------------------------------------- the scenario distributions
def test_sampled_scenarios_cover_the_papers_ranges_and_nothing_else():
    """2,000 draws from a fixed generator: every field inside its documented range and reaching both ends of it
    (every traffic count from 0 to 10, infraction draws near 0 and near 1, seeds beyond 2^30)."""
    from envs.scenario import (
        EGO_SPEED_RANGE,
        HAZARD_CAR_SPEED_RANGE,
        PEDESTRIAN_SPEED_RANGE,
        TTC_RANGE,
        sample_scenario,
    )

    rng = np.random.default_rng(7)
    specs = [sample_scenario(rng) for _ in range(2000)]
    for name, (lo, hi) in (
        ("ttc", TTC_RANGE),
        ("ego_speed", EGO_SPEED_RANGE),
        ("pedestrian_speed", PEDESTRIAN_SPEED_RANGE),
        ("hazard_car_speed", HAZARD_CAR_SPEED_RANGE),
        ("p_pedestrian", (0.0, 1.0)),
        ("p_car", (0.0, 1.0)),
    ):
        values = np.array([getattr(s, name) for s in specs])
        span = hi - lo
        assert lo <= values.min() < lo + 0.01 * span and hi - 0.01 * span < values.max() <= hi, name
    for name in ("n_cars", "n_pedestrians"):
        assert {getattr(s, name) for s in specs} == set(range(MAX_OTHERS + 1)), name
    seeds = np.array([s.seed for s in specs])
    assert seeds.min() >= 0 and 2**30 < seeds.max() < 2**31 - 1 and len(set(seeds)) == len(seeds)


def test_the_focus_mix_draws_its_hazards_speeds_and_ttcs():
    from envs.scenario import sample_focus_scenario

    rng = np.random.default_rng(3)
    specs = [sample_focus_scenario(rng, 0.75, (15.0, 30.0), (0.25, 1.1)) for _ in range(1200)]
    hazards = [s.hazard for s in specs]
    share = {h: hazards.count(h) / len(specs) for h in ("none", "pedestrian", "car", "both")}
    assert abs(share["none"] - 0.25) < 0.05 and all(abs(share[h] - 0.25) < 0.05 for h in ("pedestrian", "car", "both"))
    speeds, ttcs = np.array([s.ego_speed for s in specs]), np.array([s.ttc for s in specs])
    assert 15.0 <= speeds.min() < 15.2 and 29.8 < speeds.max() <= 30.0
    assert 0.25 <= ttcs.min() < 0.26 and 1.09 < ttcs.max() <= 1.1
    assert {s.n_cars for s in specs} == {s.n_pedestrians for s in specs} == set(range(MAX_OTHERS + 1))
    assert 2**30 < max(s.seed for s in specs) < 2**31 - 1
    # the ends of every range are allowed: only hazards, never a hazard, one speed, one TTC
    assert sample_focus_scenario(rng, 1.0).hazard != "none" and sample_focus_scenario(rng, 0.0).hazard == "none"
    one = sample_focus_scenario(rng, 0.5, (20.0, 20.0), (0.5, 0.5))
    assert (one.ego_speed, one.ttc) == (20.0, 0.5)
    # the defaults: 85 % hazards, 15-30 m/s, TTC 0.25-1.1 s
    default, explicit = np.random.default_rng(5), np.random.default_rng(5)
    for _ in range(20):
        assert sample_focus_scenario(default) == sample_focus_scenario(explicit, 0.85, (15.0, 30.0), (0.25, 1.1))
    with pytest.raises(ValueError, match=r"focus hazard_share=1.5 must be in \[0, 1\]"):
        sample_focus_scenario(rng, 1.5)
    with pytest.raises(ValueError, match=r"focus speed_range=\(30.0, 15.0\) must satisfy 0 < low <= high"):
        sample_focus_scenario(rng, 0.5, (30.0, 15.0))
    with pytest.raises(ValueError, match=r"focus ttc_range=\(0.0, 1.0\) must satisfy 0 < low <= high"):
        sample_focus_scenario(rng, 0.5, (15.0, 30.0), (0.0, 1.0))


def test_a_scenario_bank_is_its_documented_grid():
    from envs.scenario import BANK_HAZARDS, BANK_SPEEDS, BANK_TTCS
    from envs.scenario import scenario_bank as make_bank

    bank = make_bank(seed=2018)
    assert len(bank) == len(BANK_HAZARDS) * len(BANK_TTCS) * len(BANK_SPEEDS) * 20  # 20 per cell by default
    assert [e.scenario_id for e in bank] == list(range(len(bank)))
    for e in bank[:: len(bank) // 50]:
        assert (e.spec.ttc, e.spec.ego_speed, e.spec.hazard) == (e.ttc, e.speed, e.hazard)
        assert isinstance(e.speed, float) and 0 <= e.index < 20
    seeds = [e.spec.seed for e in bank]
    assert len(set(seeds)) == len(seeds) and max(seeds) > 2**30
    with pytest.raises(ValueError, match="per_cell=0 must be at least 1"):
        make_bank(per_cell=0, seed=2018)
    with pytest.raises(ValueError, match="hazard='none' must be one of"):
        make_bank(hazards=("none",), seed=2018)
