"""Tests of worldmodel.report on hand-built evaluation rows whose every aggregate is known in advance.

The synthetic bank (hazards pedestrian/car/both × TTC {0.5, 1.5} × speed {10, 30} × 4 scenarios):

* ``braking`` hits the pedestrian in every pedestrian/both scenario (injury ``inj(ttc, speed)``) and the car in every
  car/both scenario (occupant injury ``occ(speed)``); speed at collision = speed / 2.
* ``agent_r2`` hits the pedestrian in even-numbered scenarios at TTC 0.5 only (never at 1.5), never hits a car, but
  hits a pole (static, occupant injury 0.01) in odd-numbered car/both scenarios.
* ``agent_r1`` behaves like braking with twice the occupant injury, so its occupant improvement is negative.
"""

from __future__ import annotations

import json
import math
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from worldmodel import report  # noqa: E402

HAZARDS = ("pedestrian", "car", "both")
N = 4


def inj(ttc: float, speed: float) -> float:
    return speed / 100.0 * (2.0 if ttc == 0.5 else 1.0)  # 0.2, 0.6 at TTC 0.5; 0.1, 0.3 at TTC 1.5


def occ(speed: float) -> float:
    return 0.003 * speed  # 0.03 at 10 m/s, 0.09 at 30 m/s


def make_row(policy, sid, hazard, ttc, speed, **outcome):
    row = dict(
        policy=policy,
        policy_seed=0,
        scenario_id=sid,
        hazard=hazard,
        ttc=float(ttc),
        speed=float(speed),
        seed=1000 + sid,
        pedestrian_collision=0,
        vehicle_collision=0,
        static_collision=0,
        lane_departure=0,
        n_pedestrians_hit=0,
        pedestrian_injury=0.0,
        occupant_injury=0.0,
        ego_occupant_injury=0.0,
        speed_at_collision=math.nan,
        steps=30,
        return_r1=0.0,
        return_r2=0.0,
        end="horizon",
        final_speed=0.0,
    )
    row.update(outcome)
    return row


def bank(policies=("braking", "agent_r1", "agent_r2"), ttcs=(0.5, 1.5), speeds=(10, 30)):
    rows, sid = [], 0
    for hazard in HAZARDS:
        for ttc in ttcs:
            for speed in speeds:
                for k in range(N):
                    sid += 1
                    ped = hazard in ("pedestrian", "both")
                    car = hazard in ("car", "both")
                    for policy in policies:
                        out = {}
                        if policy in ("braking", "agent_r1", "oracle"):
                            if ped:
                                out.update(
                                    pedestrian_collision=1, n_pedestrians_hit=1, pedestrian_injury=inj(ttc, speed)
                                )
                            if car:
                                factor = 2.0 if policy == "agent_r1" else 1.0
                                out.update(
                                    vehicle_collision=1,
                                    occupant_injury=factor * occ(speed),
                                    ego_occupant_injury=occ(speed) / 2,
                                )
                            if ped or car:
                                out.update(speed_at_collision=speed / 2, return_r1=-1.0, return_r2=-2.0)
                        elif policy == "agent_r2":
                            if ped and ttc == 0.5 and k % 2 == 0:
                                out.update(
                                    pedestrian_collision=1,
                                    n_pedestrians_hit=1,
                                    pedestrian_injury=inj(ttc, speed),
                                    speed_at_collision=speed / 2,
                                )
                            if car and k % 2 == 1:
                                out.update(
                                    static_collision=1,
                                    lane_departure=1,
                                    occupant_injury=0.01,
                                    ego_occupant_injury=0.01,
                                    speed_at_collision=speed / 4,
                                )
                        rows.append(make_row(policy, sid, hazard, ttc, speed, **out))
    return rows


def cell(summary, policy, hazard, ttc, speed):
    hits = [
        c
        for c in summary["policies"][policy]["cells"]
        if c["hazard"] == hazard and c["ttc"] == ttc and c["speed"] == speed
    ]
    assert len(hits) == 1, hits
    return hits[0]


def table_rows(md: str, title_start: str) -> dict[str, list[str]]:
    """Label -> cell strings of the Markdown table under the heading that starts with ``title_start``."""
    section = md.split("### " + title_start, 1)[1].split("\n### ", 1)[0]
    out = {}
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("| ---"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            out[cells[0]] = cells[1:]
    return out


def no_nan(text: str):
    def reject(name):
        raise AssertionError(f"non-finite constant {name} in JSON")

    return json.loads(text, parse_constant=reject)


# ----------------------------------------------------------------------------- summary
def test_summary_numbers_and_json():
    rows = bank()
    summary = no_nan(json.dumps(report.summarize(rows), allow_nan=False))
    assert summary["grid"]["ttcs"] == [0.5, 1.5] and summary["grid"]["speeds"] == [10.0, 30.0]
    assert summary["grid"]["hazards"] == ["pedestrian", "car", "both"]
    assert summary["grid"]["policies"] == ["braking", "agent_r1", "agent_r2"]
    assert summary["grid"]["scenarios_per_cell"] == {"min": N, "max": N}

    b = cell(summary, "braking", "pedestrian", 0.5, 30.0)
    assert b["count"] == N
    assert b["pedestrian_collision_rate"] == 1.0 and b["vehicle_collision_rate"] == 0.0
    assert b["pedestrian_severe_injury"] == pytest.approx(0.6)
    assert b["mean_speed_at_collision"] == pytest.approx(15.0)

    r2 = cell(summary, "agent_r2", "pedestrian", 0.5, 30.0)
    assert r2["pedestrian_collision_rate"] == 0.5
    assert r2["pedestrian_severe_injury"] == pytest.approx(0.3)
    assert r2["mean_speed_at_collision"] == pytest.approx(15.0)  # NaN of the misses ignored

    quiet = cell(summary, "agent_r2", "pedestrian", 1.5, 10.0)  # no collision at all
    assert quiet["pedestrian_collision_rate"] == 0.0 and quiet["mean_speed_at_collision"] is None

    car = cell(summary, "agent_r2", "car", 1.5, 10.0)
    assert car["vehicle_collision_rate"] == 0.0
    assert car["static_collision_rate"] == 0.5 and car["lane_departure_rate"] == 0.5
    assert car["occupant_severe_injury"] == pytest.approx(0.005)
    assert car["mean_speed_at_collision"] == pytest.approx(2.5)

    overall = summary["policies"]["braking"]["overall"]
    assert overall["count"] == 3 * 2 * 2 * N
    assert overall["pedestrian_collision_rate"] == pytest.approx(2 / 3)
    assert overall["vehicle_collision_rate"] == pytest.approx(2 / 3)
    by_ttc = summary["policies"]["agent_r2"]["pedestrian_collision_rate_by_ttc"]
    assert [(d["ttc"], d["rate"], d["count"]) for d in by_ttc] == [(0.5, 0.5, 2 * 2 * N), (1.5, 0.0, 2 * 2 * N)]
    assert summary["policies"]["agent_r2"]["label"] == "Brake&Steer, reward 2"
    # improvement in points, same as improvement_grids
    imp = summary["improvement"]["agent_r2"]["pedestrian_collision"]
    assert imp["ttcs"] == [0.5, 1.5] and imp["values"] == [[50.0, 50.0], [100.0, 100.0]]
    assert "braking" not in summary["improvement"]


def test_summary_keys_hazard_breakdown_and_cell_order():
    summary = report.summarize(bank())
    assert set(summary) == {"schema", "grid", "baseline", "policies", "improvement"}  # no planner, no share
    assert summary["schema"] == 1 and summary["baseline"] == "braking"
    r2 = summary["policies"]["agent_r2"]
    # agent_r2 hits the pedestrian in 4 of 16 scenarios and a pole in 8 of 16 car-involving ones; in "both" the two
    # never happen in the same scenario, so 12 of 16 have some collision
    assert [
        (h["hazard"], h["count"], h["pedestrian_collision_rate"], h["static_collision_rate"], h["any_collision_rate"])
        for h in r2["by_hazard"]
    ] == [("pedestrian", 16, 0.25, 0.0, 0.25), ("car", 16, 0.0, 0.5, 0.5), ("both", 16, 0.25, 0.5, 0.75)]
    # report order: hazards as in the paper, then TTC, then speed
    assert [(c["hazard"], c["ttc"], c["speed"]) for c in r2["cells"]] == [
        (h, t, s) for h in HAZARDS for t in (0.5, 1.5) for s in (10.0, 30.0)
    ]
    both = cell(summary, "braking", "both", 0.5, 10.0)  # pedestrian and occupants hurt in the same scenario
    assert both["total_severe_injury"] == pytest.approx(inj(0.5, 10) + occ(10))

    empty = report.summarize([])
    assert empty["grid"]["scenarios_per_cell"] == {"min": 0, "max": 0} and empty["policies"] == {}


def test_any_collision_counts_every_kind_once_and_empty_cells_are_skipped():
    outcomes = [
        dict(pedestrian_collision=1, steps=10),
        dict(vehicle_collision=1, steps=20),
        dict(static_collision=1, steps=30),
        dict(pedestrian_collision=1, vehicle_collision=1, steps=40),  # two at once count once
        dict(lane_departure=1, steps=50),  # leaving the lane is not a collision
        dict(steps=None),  # an empty integer cell of the results CSV reads back as None
    ]
    rows = [make_row("braking", sid, "both", 0.5, 10, **o) for sid, o in enumerate(outcomes)]
    each = [report.summarize([r])["policies"]["braking"]["overall"]["any_collision_rate"] for r in rows]
    assert each == [1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
    overall = report.summarize(rows)["policies"]["braking"]["overall"]
    assert overall["any_collision_rate"] == pytest.approx(4 / 6) and overall["count"] == 6
    assert overall["mean_steps"] == 30.0  # the None is left out, not read as 0 (that would give 25)


def test_seed_spread_and_share_against_a_baseline_of_any_name():
    """The baseline is whichever policy the caller names, here "cautious" (no "braking" rows at all): improvement,
    share and the per-seed spread must all be measured against it. Two seeds are enough for a spread."""
    rows = []
    for sid in range(2):
        rows.append(make_row("cautious", sid, "pedestrian", 0.5, 10, pedestrian_collision=1, pedestrian_injury=0.4))
        rows.append(make_row("oracle", sid, "pedestrian", 0.5, 10))
    # seed 0 halves the baseline's risk (share 50 %), seed 1 misses one pedestrian and quarters it (share 75 %)
    for seed, hits in ((0, (0.2, 0.2)), (1, (0.2, 0.0))):
        for sid, injury in enumerate(hits):
            rows.append(
                make_row(
                    "agent",
                    sid,
                    "pedestrian",
                    0.5,
                    10,
                    policy_seed=seed,
                    pedestrian_collision=int(injury > 0),
                    pedestrian_injury=injury,
                )
            )
    summary = report.summarize(rows, baseline="cautious")
    assert summary["baseline"] == "cautious"
    assert summary["improvement"]["agent"]["pedestrian_injury"]["values"] == [[pytest.approx(25.0)]]
    share = summary["achievable_share"]
    assert set(share) == {"ceiling", "definition", "policies"} and share["ceiling"] == "oracle"
    assert share["policies"]["agent"]["overall"] == pytest.approx(62.5)  # pooled risk 0.15 of 0.4
    assert share["policies"]["agent"]["cells"]["values"] == [[pytest.approx(62.5)]]
    assert share["policies"]["oracle"]["overall"] == pytest.approx(100.0)

    entry = summary["policies"]["agent"]
    assert entry["seeds"] == [0, 1]
    assert "seed_spread" not in summary["policies"]["cautious"]
    spread = entry["seed_spread"]
    assert spread["seeds"] == [0, 1]
    assert spread["by_seed"]["0"]["achievable_share"] == pytest.approx(50.0)
    assert spread["by_seed"]["1"]["achievable_share"] == pytest.approx(75.0)
    assert spread["spread"]["achievable_share"] == {
        "mean": pytest.approx(62.5),
        "std": pytest.approx(25.0 / math.sqrt(2)),  # n - 1 in the denominator
        "min": pytest.approx(50.0),
        "max": pytest.approx(75.0),
    }
    assert spread["spread"]["pedestrian_collision_rate"] == {
        "mean": 0.75,
        "std": pytest.approx(0.5 / math.sqrt(2)),
        "min": 0.5,
        "max": 1.0,
    }
    assert spread["spread"]["pedestrian_severe_injury"]["mean"] == pytest.approx(0.15)


def test_seed_spread_measures_against_braking_by_default():
    """published.bank_figures calls seed_spread without a baseline: each seed's share is then against "braking".
    Braking 0.4 on both scenarios, the planner 0: seed 0 halves the risk (share 50 %), seed 1 quarters it (75 %)."""
    rows = []
    for sid in range(2):
        rows.append(make_row("braking", sid, "pedestrian", 0.5, 10, pedestrian_collision=1, pedestrian_injury=0.4))
        rows.append(make_row("oracle", sid, "pedestrian", 0.5, 10))
    for seed, hits in ((0, (0.2, 0.2)), (1, (0.2, 0.0))):
        rows += [
            make_row("agent", sid, "pedestrian", 0.5, 10, policy_seed=seed, pedestrian_injury=injury)
            for sid, injury in enumerate(hits)
        ]
    spread = report.seed_spread(rows, "agent")
    assert spread == report.seed_spread(rows, "agent", "braking")
    assert [spread["by_seed"][s]["achievable_share"] for s in ("0", "1")] == [pytest.approx(50.0), pytest.approx(75.0)]


# ----------------------------------------------------------------------------- tables
def test_tables_values_layout_and_references():
    md = report.tables_markdown(bank())

    t1 = table_rows(md, "Table I.")
    labels = list(t1)
    assert labels[0] == "Policy type" and labels[1] == "*speed (m/s)*"
    assert labels[2:5] == ["Straight-line braking", "Brake&Steer, reward 1", "Brake&Steer, reward 2"]
    assert t1["Policy type"] == ["TTC 0.5 s", "", "TTC 1.5 s", ""]
    assert t1["*speed (m/s)*"] == ["10", "30", "10", "30"]
    assert t1["Straight-line braking"] == ["20.000", "60.000", "10.000", "30.000"]
    assert t1["Brake&Steer, reward 2"] == ["10.000", "30.000", "0.000", "0.000"]
    assert t1["Straight-line braking (paper, CARLA)"] == ["0.886", "6.08", "0.0", "0.0"]
    assert t1["Brake&Steer, reward 2 (paper, CARLA)"] == ["0.054", "3.487", "0.0", "0.0"]

    t2 = table_rows(md, "Table II.")
    assert t2["Straight-line braking"] == ["2.000", "6.000", "2.000", "6.000"]
    assert t2["Brake&Steer, reward 1"] == ["4.000", "12.000", "4.000", "12.000"]
    assert t2["Brake&Steer, reward 2"] == ["0.333", "0.333", "0.333", "0.333"]
    assert t2["Brake&Steer, reward 1 (paper, CARLA)"] == ["0.001", "0.579", "0.0", "0.0"]

    t3 = table_rows(md, "Table III.")
    assert t3["TTC (s)"] == ["0.5", "1.5"]
    assert t3["Straight-line braking"] == ["100.0", "100.0"]
    assert t3["Brake&Steer, reward 2"] == ["50.0", "0.0"]
    assert t3["Porav & Newman R2 (paper)"] == ["21.8", "0.0"]
    assert t3["Chae et al. (paper)"] == ["NA", "0.0"]

    # each table states how many scenarios a cell averages
    sections = md.split("\n### ")
    assert "averages 8 scenarios" in sections[1]  # pedestrian + both, 4 each
    assert "averages 12 scenarios" in sections[2] and "static" in sections[2]  # all hazards
    assert "averages 16 scenarios" in sections[3]  # 2 speeds x 2 hazards x 4


def test_tables_subset_grid_references_only_where_the_paper_has_them():
    rows = bank(ttcs=(0.75, 1.3), speeds=(20, 30))
    md = report.tables_markdown(rows)
    t1 = table_rows(md, "Table I.")
    assert t1["Policy type"] == ["TTC 0.75 s", "", "TTC 1.3 s", ""]
    assert t1["Straight-line braking (paper, CARLA)"] == ["0.360", "1.650", "—", "—"]
    t3 = table_rows(md, "Table III.")
    assert t3["Chae et al. (paper)"] == ["NA", "0.74"]

    md = report.tables_markdown(bank(ttcs=(0.9, 1.1), speeds=(10, 20)))
    t1 = table_rows(md, "Table I.")
    assert not any("(paper, CARLA)" in label for label in t1)  # no overlap with the paper's columns
    assert table_rows(md, "Table III.")["Chae et al. (paper)"] == ["61.29", "18.85"]


def test_other_policies_follow_the_named_ones():
    rows = bank(policies=("oracle", "agent_r2", "braking"))
    md = report.tables_markdown(rows)
    assert list(table_rows(md, "Table III."))[1:4] == [
        "Straight-line braking",
        "Brake&Steer, reward 2",
        "Privileged planner (oracle)",
    ]
    assert list(report.improvement_grids(rows)) == ["agent_r2", "oracle"]


# ----------------------------------------------------------------------------- improvement grids
def test_improvement_grids_values_and_sign():
    grids = report.improvement_grids(bank())
    assert set(grids) == {"agent_r1", "agent_r2"}
    assert set(grids["agent_r2"]) == {"pedestrian_collision", "pedestrian_injury", "car_collision", "occupant_injury"}

    ttcs, speeds, arr = grids["agent_r2"]["pedestrian_collision"]
    assert list(ttcs) == [0.5, 1.5] and list(speeds) == [10.0, 30.0]
    assert arr.shape == (2, 2)  # rows = TTC, columns = speed
    np.testing.assert_allclose(arr, [[50, 50], [100, 100]])
    np.testing.assert_allclose(grids["agent_r2"]["pedestrian_injury"][2], [[10, 30], [10, 30]])
    np.testing.assert_allclose(grids["agent_r2"]["car_collision"][2], [[100, 100], [100, 100]])
    np.testing.assert_allclose(grids["agent_r2"]["occupant_injury"][2], [[2 - 1 / 3, 6 - 1 / 3]] * 2)

    # agent_r1: same collisions as braking (zero improvement), doubled occupant injury (negative = worse)
    np.testing.assert_allclose(grids["agent_r1"]["pedestrian_collision"][2], 0.0)
    np.testing.assert_allclose(grids["agent_r1"]["occupant_injury"][2], [[-2, -6], [-2, -6]])


def test_improvement_grid_nan_where_no_scenario_and_missing_baseline():
    rows = [r for r in bank() if r["hazard"] == "car"]
    grids = report.improvement_grids(rows)
    assert np.isnan(grids["agent_r2"]["pedestrian_collision"][2]).all()
    np.testing.assert_allclose(grids["agent_r2"]["car_collision"][2], 100.0)
    with pytest.raises(ValueError, match="baseline"):
        report.improvement_grids([r for r in rows if r["policy"] != "braking"])


def test_episode_endings_from_recorded_ends_and_inferred_for_older_rows(tmp_path, capsys):
    """experiments/episode_endings.py: rows that record ``end`` and ``final_speed`` are classified from them; rows
    without (as committed before the columns) by their collisions and their steps against the env's horizon."""
    from envs.env import DT, horizon_steps
    from experiments import episode_endings as ee

    assert horizon_steps(0.5) == 53 and horizon_steps(1.5) == 68  # (TTC + 3 s) at 15 steps a second, rounded up

    def ending(**kw):
        return ee.ending(make_row("braking", 1, "car", 0.5, 20.0, **kw), 0.5, DT, 3.0)

    assert ending(end="crash", vehicle_collision=1, static_collision=1) == ee.VEHICLE
    assert ending(end="crash", static_collision=1) == ee.STATIC
    assert ending(end="horizon", steps=53, final_speed=0.2) == ee.STOPPED
    assert ending(end="horizon", steps=53, final_speed=3.0) == ee.MOVING
    assert ending(end="left_scene", steps=40) == ee.LEFT
    assert ending(end="", vehicle_collision=1, steps=20) == ee.VEHICLE
    assert ending(end="", static_collision=1, steps=20) == ee.STATIC
    assert ending(end="", steps=52) == ee.LEFT
    assert ending(end="", steps=53, pedestrian_collision=1) == ee.TIME_LIMIT  # a pedestrian hit ends nothing
    with pytest.raises(ValueError, match="horizon"):
        ending(end="", steps=54)

    rows = [make_row("braking", 1, "car", 0.5, 20.0, end="left_scene", steps=40, return_r2=-0.25)]
    rows.append(make_row("braking", 2, "car", 0.5, 20.0, end="horizon", steps=53, final_speed=0.0))
    report.write_results_csv(rows, tmp_path / "results.csv")
    assert ee.main([str(tmp_path / "results.csv")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("| braking"))
    # crashes (vehicle, static), stopped, left, moving, pedestrian hits, R2 cost of all and of those that left
    assert line == "| braking | 2 | 0.0 | 0.0 | 50.0 | 50.0 | 0.0 | 0.0 | 0.1250 | 0.2500 |"


# ----------------------------------------------------------------------------- CSV
def test_csv_round_trip(tmp_path):
    rows = bank(policies=("braking", "agent_r2"))
    for r in rows:  # an all-digit hash must come back as the same string, not as a number
        r.update({c: "" if r["policy"] == "braking" else "012345678901" for c in report.MODEL_COLUMNS})
    rows[0]["extra_note"] = "x"
    rows[1]["pedestrian_injury"] = np.float32(0.125)  # numpy scalars are written as plain numbers
    rows[1]["steps"] = np.int64(17)
    rows[2]["return_r2"] = -1 / 3  # needs all 17 significant digits to survive
    rows[2]["speed_at_collision"] = 12.345678901234567
    path = tmp_path / "results.csv"
    report.write_results_csv(rows, path)
    assert os.listdir(tmp_path) == ["results.csv"]  # no temporary file left behind
    back = report.read_results_csv(path)
    assert len(back) == len(rows)
    for a, b in zip(rows, back):
        for key in report.COLUMNS:
            va, vb = a[key], b[key]
            assert (
                type(vb)
                is {
                    **{k: int for k in report.INT_COLUMNS},
                    **{k: float for k in report.FLOAT_COLUMNS},
                    **{k: str for k in report.STR_COLUMNS},
                }[key]
            ), (key, vb)
            if isinstance(va, (float, np.floating)) and math.isnan(va):
                assert math.isnan(vb), key
            else:
                assert vb == va, (key, va, vb)
    assert back[0]["extra_note"] == "x" and back[1]["extra_note"] is None
    assert any(math.isnan(r["speed_at_collision"]) for r in back)
    assert report.summarize(back) == report.summarize(rows)
    assert report.tables_markdown(back) == report.tables_markdown(rows)


# ----------------------------------------------------------------------------- figure and files
def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def heatmap_titles(fig) -> list[str]:
    return [ax.get_title() for ax in fig.axes if ax.get_title()]


def test_render_report_files_and_tensorboard(tmp_path):
    """Tables, heatmaps and TensorBoard; ``summary.json`` is left to the evaluation, which writes it last."""
    from torch.utils.tensorboard import SummaryWriter

    rows = bank(policies=("braking", "agent_r1", "agent_r2", "oracle"))
    writer = SummaryWriter(log_dir=str(tmp_path / "tb"))
    try:
        summary = report.render_report(rows, tmp_path / "out", tb_writer=writer, step=3)
    finally:
        writer.close()
    out = tmp_path / "out"
    assert sorted(os.listdir(out)) == ["heatmaps.png", "tables.md"]
    assert no_nan(json.dumps(summary, allow_nan=False)) == json.loads(json.dumps(report.summarize(rows)))
    assert (out / "tables.md").read_text() == report.tables_markdown(rows)
    data = (out / "heatmaps.png").read_bytes()
    width, height = png_size(data)
    assert width >= 800 and height >= 300 and 20_000 < len(data) < 5_000_000

    events = b"".join(p.read_bytes() for p in (tmp_path / "tb").rglob("events.out.tfevents.*"))
    for tag in (b"report/heatmaps", b"report/tables", b"report/agent_r2/pedestrian_collision_rate"):
        assert tag in events, tag
    assert b"\x89PNG" in events  # the figure went in as an image


def test_heatmap_layout_rows_columns_and_shared_symmetric_range():
    # "a_swerve" (no collisions at all) sorts before agent_r1 alphabetically but must come after the named policies
    rows = bank(policies=("oracle", "a_swerve", "agent_r2", "braking", "agent_r1"))
    fig = report.heatmaps_figure(rows)
    titles = heatmap_titles(fig)
    assert len(titles) == 4 * 5  # with the planner present, column (e) is the share of the achievable improvement
    assert titles[0].startswith("Brake&Steer, reward 1") and "(a)" in titles[0] and "(d)" in titles[3]
    assert "(e) share of achievable" in titles[4]
    assert titles[5].startswith("Brake&Steer, reward 2")
    assert titles[10].startswith("Privileged planner") and titles[15].startswith("a_swerve")
    assert "improvement" in fig._suptitle.get_text()
    images = [ax.images[0] for ax in fig.axes if ax.images]
    assert len(images) == 20
    # this bank's planner is no better than braking anywhere, so no share is defined
    assert [t.get_text() for t in [ax for ax in fig.axes if ax.images][4].texts] == ["n/a"] * 4
    images = [im for k, im in enumerate(images) if k % 5 != 4]
    for col in range(4):
        clims = {images[row * 4 + col].get_clim() for row in range(4)}
        assert len(clims) == 1  # shared down the column
        lo, hi = clims.pop()
        assert lo == -hi and hi > 0  # centred at zero
    assert images[0].get_clim() == (-100.0, 100.0)  # column (a) peaks at a 100-point gain
    assert images[3].get_clim() == pytest.approx((-6.0, 6.0))  # column (d): agent_r1's 6-point loss, a_swerve's gain
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts == ["0.0"] * 4  # agent_r1 pedestrian collision: no change anywhere


def test_baseline_only_and_no_baseline_never_crash(tmp_path):
    rows = bank(policies=("braking",))
    summary = report.render_report(rows, tmp_path)
    assert summary["improvement"] == {} and list(summary["policies"]) == ["braking"]
    fig = report.heatmaps_figure(rows)
    titles = heatmap_titles(fig)
    assert len(titles) == 4 and all(t.startswith("Straight-line braking") for t in titles)
    assert "absolute" in fig._suptitle.get_text()
    images = [ax.images[0] for ax in fig.axes if ax.images]
    np.testing.assert_allclose(images[0].get_array().filled(np.nan), [[100, 100], [100, 100]])  # collision %
    png_size((tmp_path / "heatmaps.png").read_bytes())
    assert table_rows((tmp_path / "tables.md").read_text(), "Table III.")["Straight-line braking"] == ["100.0", "100.0"]

    agents = bank(policies=("agent_r2",))
    assert report.improvement_grids(agents, baseline="agent_r2") == {}
    fig = report.heatmaps_figure(agents)  # baseline missing: absolute values, no exception
    assert "missing" in fig._suptitle.get_text()

    empty = report.render_report([], tmp_path / "empty")
    assert empty["policies"] == {} and empty["grid"]["n_rows"] == 0
    png_size((tmp_path / "empty" / "heatmaps.png").read_bytes())


# ----------------------------------------------------------------------------- the planner and seed sweeps
def test_share_of_achievable_improvement():
    """Braking hurts 0.4 per pedestrian scenario, the planner 0.1, agent_r1 0.25 (half-way), agent_r2 0.7."""
    rows = []
    for sid, (hazard, ttc) in enumerate([("pedestrian", 0.5), ("pedestrian", 1.5), ("car", 0.5), ("car", 1.5)]):
        for policy, injury in (("braking", 0.4), ("oracle", 0.1), ("agent_r1", 0.25), ("agent_r2", 0.7)):
            ped = hazard == "pedestrian" and ttc == 0.5  # elsewhere nobody is hurt, so nothing is achievable
            rows.append(make_row(policy, sid, hazard, ttc, 10, pedestrian_injury=injury if ped else 0.0))
    shares = report.achievable_share_grids(rows)
    assert list(shares) == ["agent_r1", "agent_r2", "oracle"]
    ttcs, speeds, arr = shares["agent_r1"]
    assert ttcs == [0.5, 1.5] and speeds == [10.0]
    assert arr[0, 0] == pytest.approx(50.0) and np.isnan(arr[1, 0])
    assert shares["agent_r2"][2][0, 0] == pytest.approx(-100.0)  # worse than braking: negative
    assert shares["oracle"][2][0, 0] == pytest.approx(100.0)
    summary = report.summarize(rows)
    assert summary["achievable_share"]["policies"]["agent_r1"]["overall"] == pytest.approx(50.0)
    assert summary["achievable_share"]["policies"]["agent_r1"]["cells"]["values"] == [[pytest.approx(50.0)], [None]]
    table = table_rows(report.tables_markdown(rows), "Table IV.")
    assert table["Brake&Steer, reward 1: share (%)"] == ["50", "50", "—"]
    assert table["Brake&Steer, reward 2: share (%)"][0] == "-100"
    # agent_r2 is above braking in the one cell where anyone is hurt; agent_r1 nowhere
    above = report.cells_above_baseline(rows, "agent_r2")
    assert above == [{"ttc": 0.5, "speed": 10.0, "policy": 35.0, "baseline": 20.0, "planner_gain": pytest.approx(15.0)}]
    assert report.cells_above_baseline(rows, "agent_r1") == []
    cells = table_rows(report.tables_markdown(rows), "Cells where")
    assert cells["Brake&Steer, reward 2"] == ["10 m/s, 0.5 s: 35.00 / 20.00 (planner gain 15.00)", "none"]
    assert cells["Brake&Steer, reward 1"] == ["none", "none"]
    # without the planner there is no ceiling and no share
    assert report.achievable_share_grids([r for r in rows if r["policy"] != "oracle"]) == {}
    assert "Table IV." not in report.tables_markdown([r for r in rows if r["policy"] != "oracle"])


def test_seed_sweep_reports_mean_and_spread(tmp_path):
    rows = []
    for seed, hits in ((0, 1), (1, 0), (2, 1)):  # seed 1 never hits the pedestrian
        for sid in range(4):
            rows.append(
                make_row(
                    "agent_r1",
                    sid,
                    "pedestrian",
                    0.5,
                    10,
                    policy_seed=seed,
                    pedestrian_collision=hits if sid < 2 else 0,
                )
            )
    rows += [make_row("braking", sid, "pedestrian", 0.5, 10, pedestrian_collision=1) for sid in range(4)]
    summary = report.summarize(rows)
    entry = summary["policies"]["agent_r1"]
    assert entry["seeds"] == [0, 1, 2] and summary["policies"]["braking"]["seeds"] == [0]
    assert "seed_spread" not in summary["policies"]["braking"]
    spread = entry["seed_spread"]["spread"]["pedestrian_collision_rate"]
    assert spread["mean"] == pytest.approx(1 / 3) and spread["std"] == pytest.approx(np.std([0.5, 0, 0.5], ddof=1))
    assert (spread["min"], spread["max"]) == (0.0, 0.5)
    assert entry["seed_spread"]["by_seed"]["1"]["pedestrian_collision_rate"] == 0.0
    assert entry["overall"]["pedestrian_collision_rate"] == pytest.approx(1 / 3)  # pooled = mean over seeds
    table = table_rows(report.tables_markdown(rows), "Spread over training seeds")
    assert table["Brake&Steer, reward 1"][:2] == ["0, 1, 2", "33.3 ± 28.9 (0.0–50.0)"]
    # the seed survives the CSV round trip
    assert [r["policy_seed"] for r in report.read_results_csv(report.write_results_csv(rows, tmp_path / "r.csv"))][
        :5
    ] == [0] * 4 + [1]


def test_paired_bootstrap_by_hand():
    """Share and difference against braking with intervals: a policy equal to braking has share 0 and difference
    0 in every resample; one that halves braking's risk on every scenario has share 50 and a negative difference
    whose interval excludes 0; seeds are averaged per scenario first."""
    from worldmodel.report import paired_bootstrap

    def rows(policy, risks, seed=0):
        return [
            {"policy": policy, "scenario_id": i, "pedestrian_injury": r, "occupant_injury": 0.0, "policy_seed": seed}
            for i, r in enumerate(risks)
        ]

    braking = [0.2, 0.4, 0.2, 0.6]
    base = rows("braking", braking) + rows("oracle", [0.0] * 4)
    same = paired_bootstrap(base + rows("agent", braking), "agent", n=200)
    assert same["share"] == 0.0 and same["share_ci95"] == [0.0, 0.0] and same["difference_ci95"] == [0.0, 0.0]
    # two seeds that average to half of braking's risk
    half = base + rows("agent", [0.0, 0.4, 0.2, 0.6], 0) + rows("agent", [0.2, 0.0, 0.0, 0.0], 1)
    out = paired_bootstrap(half, "agent", n=500)
    assert out["share"] == pytest.approx(50.0) and out["difference_pts"] == pytest.approx(-17.5)
    assert out["difference_ci95"][1] < 0 and out["scenarios"] == 4


def test_paired_bootstrap_share_has_the_sign_of_the_improvement(tmp_path):
    """On a bank read back from the results CSV, with per-scenario risks where the planner beats braking: a policy
    halfway between the two on every scenario keeps a share of exactly 50 % in every resample; one that adds a crash
    to every braking outcome has a negative share whose whole interval lies below 0 (and a positive difference);
    the planner itself has 100 %; one that is either braking or the planner per scenario stays within [0, 100]."""
    # (pedestrian, occupant) injury per scenario
    braking = [(0.6, 0.0), (0.3, 0.05), (0.0, 0.09), (0.8, 0.0), (0.2, 0.03), (0.5, 0.0)]
    oracle = [(0.1, 0.01), (0.0, 0.0), (0.0, 0.02), (0.2, 0.0), (0.2, 0.0), (0.0, 0.0)]
    extra = [0.05, 0.02, 0.01, 0.04, 0.03, 0.05]  # occupant injury a worse policy adds, e.g. from hitting a pole
    hazards = ["pedestrian", "both", "car", "pedestrian", "both", "pedestrian"]

    def rows(policy, risks):
        return [
            make_row(policy, sid, hazard, 0.5 + 0.25 * sid, 10 + 4 * sid, pedestrian_injury=p, occupant_injury=o)
            for sid, (hazard, (p, o)) in enumerate(zip(hazards, risks))
        ]

    halfway = [((pb + po) / 2, (ob + oo) / 2) for (pb, ob), (po, oo) in zip(braking, oracle)]
    worse = [(p, o + e) for (p, o), e in zip(braking, extra)]
    mixed = [o if sid % 2 else b for sid, (b, o) in enumerate(zip(braking, oracle))]
    written = rows("braking", braking) + rows("oracle", oracle) + rows("halfway", halfway) + rows("worse", worse)
    written += rows("mixed", mixed) + rows("planner_again", oracle)
    bank = report.read_results_csv(report.write_results_csv(written, tmp_path / "results.csv"))

    total = lambda risks: sum(p + o for p, o in risks) / len(risks)  # noqa: E731
    gain = total(braking) - total(oracle)
    assert gain > report.MIN_ACHIEVABLE_GAIN  # else every share is n/a and nothing below is tested

    half = report.paired_bootstrap(bank, "halfway", n=400)
    assert half["scenarios"] == 6
    assert half["share"] == pytest.approx(50.0)
    lo, hi = half["share_ci95"]
    assert 0.0 < lo <= 50.0 + 1e-9 and 50.0 - 1e-9 <= hi
    assert half["difference_pts"] == pytest.approx(-50.0 * gain)
    assert half["difference_ci95"][1] < 0.0

    bad = report.paired_bootstrap(bank, "worse", n=400)
    expected = -100.0 * (sum(extra) / len(extra)) / gain
    assert bad["share"] == pytest.approx(expected) and expected < 0.0
    assert bad["share"] == pytest.approx(report.overall_achievable_share(bank, "worse"))
    assert bad["share_ci95"][0] <= bad["share_ci95"][1] < 0.0
    assert bad["difference_pts"] == pytest.approx(100.0 * sum(extra) / len(extra))
    assert bad["difference_ci95"][0] > 0.0

    top = report.paired_bootstrap(bank, "planner_again", n=400)
    assert top["share"] == pytest.approx(100.0)
    assert top["share_ci95"] == pytest.approx([100.0, 100.0])

    # between braking and the planner on every scenario, no resample can leave [0, 100]
    either = report.paired_bootstrap(bank, "mixed", n=400)
    assert -1e-9 <= either["share_ci95"][0] <= either["share_ci95"][1] <= 100.0 + 1e-9
    assert 0.0 < either["share"] < 100.0


def test_cells_above_baseline_lists_small_excesses_but_not_float_noise():
    cases = {  # (ttc, speed): (braking, agent) as (pedestrian, occupant) injury
        (0.5, 10): ((0.2, 0.0), (0.205, 0.0)),  # half a point riskier: listed
        (0.5, 30): ((0.3, 0.0), (0.1, 0.2)),  # the same 0.3, summed in another order: 0.30000000000000004
        (1.5, 10): ((0.1, 0.0), (0.0, 0.0)),
    }
    rows = []
    for sid, ((ttc, speed), risks) in enumerate(cases.items()):
        for policy, (p, o) in zip(("braking", "agent"), risks):
            rows.append(make_row(policy, sid, "pedestrian", ttc, speed, pedestrian_injury=p, occupant_injury=o))
    (above,) = report.cells_above_baseline(rows, "agent")
    assert (above["ttc"], above["speed"]) == (0.5, 10.0)
    assert above["policy"] == pytest.approx(20.5) and above["baseline"] == pytest.approx(20.0)
    assert math.isnan(above["planner_gain"])  # no planner rows, so no gain to show


def risk_rows(policy, risks, seed=0, first_id=0):
    """One pedestrian scenario per entry of ``risks``, a total risk or a (pedestrian, occupant) pair."""
    rows = []
    for sid, risk in enumerate(risks, start=first_id):
        p, o = risk if isinstance(risk, tuple) else (risk, 0.0)
        rows.append(
            make_row(policy, sid, "pedestrian", 0.5, 10, policy_seed=seed, pedestrian_injury=p, occupant_injury=o)
        )
    return rows


def test_paired_bootstrap_intervals_enumerated_on_two_scenarios():
    """Two scenarios, so a resample is {0, 0}, {1, 1} (a quarter each) or one of each (half). Scenario 0: braking
    0.4, planner 0, agent 0.2. Scenario 1: braking 0.2, planner 0.2 (nothing achievable), agent 0.2 + 0.1 occupant.
    Shares: {0, 0} 50 %, mixed 25 %, {1, 1} undefined (no gain): a quarter of the resamples have no share, so the
    share has no interval either. Differences (points): {0, 0} -20, mixed -5, {1, 1} +10. Each value covers at
    least a quarter of the resamples, so the 2.5 and 97.5 percentiles are the extreme values for any seed."""
    rows = risk_rows("braking", [0.4, 0.2]) + risk_rows("oracle", [0.0, 0.2]) + risk_rows("agent", [0.2, (0.2, 0.1)])
    # scenarios that not all three policies ran are left out, whichever policy lacks them
    rows += risk_rows("oracle", [0.0], first_id=7) + risk_rows("agent", [0.0], first_id=8)
    out = report.paired_bootstrap(rows, "agent", n=1000)
    assert out["scenarios"] == 2
    assert out["share"] == pytest.approx(25.0)  # (0.3 - 0.25) / (0.3 - 0.1)
    assert out["difference_pts"] == pytest.approx(-5.0)
    assert all(math.isnan(x) for x in out["share_ci95"])
    assert out["difference_ci95"] == pytest.approx([-20.0, 10.0])
    # one scenario alone has a share (50 %) but cannot be resampled: no interval
    alone = report.paired_bootstrap([r for r in rows if r["scenario_id"] == 0], "agent", n=200)
    assert alone["share"] == pytest.approx(50.0) and all(math.isnan(x) for x in alone["share_ci95"])

    with pytest.raises(ValueError, match="agent, braking and oracle"):
        report.paired_bootstrap(risk_rows("braking", [0.4]) + risk_rows("oracle", [0.0]), "agent")


def test_paired_bootstrap_interval_tails():
    """Braking 0.5 and planner 0.1 on every scenario, so each resample's gain is 0.4 and its share is
    -2.5 × its difference in points. A policy that changes the risk by ``k`` points on 3 of ``k`` scenarios moves a
    resample by m points, m ~ Binomial(k, 3/k) draws of the changed scenarios. For k = 12, P(m = 0) = 3.2 % and
    P(m <= 5) = 94.6 %, P(m <= 6) = 98.6 %: the 2.5th percentile of m is 0 (the 3.5th would be 1) and the 97.5th is
    6. For k = 7, P(m = 0) = 2.0 % and P(m = 1) = 10.4 %: the 2.5th percentile is 1 (the 1.5th would be 0). Enough
    resamples keep every count several standard errors from these edges."""
    n = 50_000
    base = risk_rows("braking", [0.5] * 12) + risk_rows("oracle", [0.1] * 12)

    def run(k, step):
        risks = [0.5] * (k - 3) + [0.5 + step * k / 100] * 3
        return report.paired_bootstrap(base + risk_rows("agent", risks), "agent", n=n)

    worse = run(12, +1)
    assert worse["difference_ci95"] == pytest.approx([0.0, 6.0])
    assert worse["share_ci95"] == pytest.approx([-15.0, 0.0])
    better = run(12, -1)
    assert better["difference_ci95"] == pytest.approx([-6.0, 0.0])
    assert better["share_ci95"] == pytest.approx([0.0, 15.0])
    # k = 7: only the ends near the 2 % bin; the other ends sit within 0.2 % of a bin edge
    worse = run(7, +1)
    assert worse["difference_ci95"][0] == pytest.approx(1.0) and worse["share_ci95"][1] == pytest.approx(-2.5)
    better = run(7, -1)
    assert better["difference_ci95"][1] == pytest.approx(-1.0) and better["share_ci95"][0] == pytest.approx(2.5)


def test_paired_bootstrap_defaults_and_seed():
    """experiments/ablation.py relies on the defaults: 2000 resamples drawn with seed 0, the same interval on every
    call; another seed or count gives another interval on a bank whose resamples nearly all differ."""
    braking = [0.6113, 0.3729, 0.0571, 0.8307, 0.2903, 0.4787, 0.7141, 0.1319]
    agent = [0.3037, 0.3101, 0.0443, 0.2017, 0.2539, 0.1061, 0.5573, 0.0211]
    rows = risk_rows("braking", braking) + risk_rows("oracle", [0.2 * b for b in braking]) + risk_rows("agent", agent)
    default = report.paired_bootstrap(rows, "agent")
    assert default == report.paired_bootstrap(rows, "agent", n=2000, seed=0)
    for other in (report.paired_bootstrap(rows, "agent", seed=1), report.paired_bootstrap(rows, "agent", n=2001)):
        assert other["share"] == default["share"] and other["difference_pts"] == default["difference_pts"]
        assert other["share_ci95"] != default["share_ci95"]
        assert other["difference_ci95"] != default["difference_ci95"]


def test_a_bank_with_too_little_to_gain_has_no_share_and_no_interval():
    """A planner 0.02 points better than braking leaves no share to speak of: the point estimate is n/a, and so is
    its interval, rather than a ratio of two near-zero gaps (thousands of %)."""
    rows = []
    for sid, (b, o, a) in enumerate(((0.3, 0.2998, 0.31), (0.2, 0.2, 0.2))):
        for name, risk in (("braking", b), ("oracle", o), ("agent", a)):
            rows.append(make_row(name, sid, "pedestrian", 1.0, 10.0, pedestrian_injury=risk))
    out = report.paired_bootstrap(rows, "agent", n=500)
    assert math.isnan(out["share"]) and all(math.isnan(x) for x in out["share_ci95"])
    assert out["difference_pts"] == pytest.approx(0.5)
    # a bank whose mean gap falls short while some resamples' gaps do not: still no interval without a share
    rows = []
    for sid, (b, o) in enumerate(((0.009, 0.0), (0.2, 0.2))):
        for name, risk in (("braking", b), ("oracle", o), ("agent", b)):
            rows.append(make_row(name, sid, "pedestrian", 1.0, 10.0, pedestrian_injury=risk))
    out = report.paired_bootstrap(rows, "agent", n=500)
    assert math.isnan(out["share"]) and all(math.isnan(x) for x in out["share_ci95"])


def test_a_gap_of_exactly_the_minimum_has_a_share():
    """n/a only below MIN_ACHIEVABLE_GAIN: a planner exactly that much better than braking gives shares."""
    gap = report.MIN_ACHIEVABLE_GAIN
    rows = [  # two scenarios alike, so that the bootstrap has something to resample and every resample the same gap
        make_row(name, sid, "pedestrian", 1.0, 10.0, pedestrian_injury=risk)
        for sid in (0, 1)
        for name, risk in (("braking", gap), ("oracle", 0.0), ("agent", gap / 2))
    ]
    assert report.overall_achievable_share(rows, "agent") == pytest.approx(50.0)
    out = report.paired_bootstrap(rows, "agent", n=50)
    assert out["share"] == pytest.approx(50.0) and out["share_ci95"] == pytest.approx([50.0, 50.0])


def test_the_sign_flip_p_is_the_one_scipy_computes_from_the_same_draws():
    """``paired_permutation_p`` reads scipy's own random flips directly: its p-value equals
    ``scipy.stats.permutation_test``'s, with and without ties, for an odd number of draws too."""
    from scipy.stats import permutation_test

    from worldmodel.stats import paired_permutation_p

    rng = np.random.default_rng(7)
    cases = [(20, "normal", 2000), (301, "normal", 2001), (300, "ties", 2000), (1000, "ties", 1000)]
    for n, kind, flips in cases:
        d = rng.normal(0.05, 1.0, n) if kind == "normal" else rng.integers(-1, 2, n).astype(float)
        for seed in (0, 1):
            expected = permutation_test(
                (d,),
                lambda x, axis: np.mean(x, axis=axis),
                permutation_type="samples",
                n_resamples=flips,
                alternative="two-sided",
                vectorized=True,
                rng=np.random.default_rng(seed),
            ).pvalue
            assert paired_permutation_p(d, np.zeros(n), flips=flips, seed=seed) == float(expected), (n, kind, seed)


def test_wilson_intervals_and_paired_permutation_p_by_hand():
    """worldmodel/stats.py against values computed by hand: the Wilson interval's closed form at z = 1.959964,
    and a sign-flip test small enough that scipy enumerates all 2^6 flips."""
    from worldmodel.stats import paired_permutation_p, wilson

    z = 1.959963984540054
    for k, n in ((0, 10), (5, 10), (37, 40)):
        p = k / n
        centre = (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
        assert wilson(k, n) == pytest.approx((100 * (centre - half), 100 * (centre + half)), abs=1e-9)
    assert all(math.isnan(x) for x in wilson(0, 0))
    # differences +0.5, -0.5, +1, +1, +0.5, +1 (mean 0.583): 8 of the 64 sign patterns reach |mean| >= 0.583
    a, b = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [0.5, 2.5, 2.0, 3.0, 4.5, 5.0]
    assert paired_permutation_p(a, b) == pytest.approx(8 / 64)
    assert paired_permutation_p(b, a) == pytest.approx(8 / 64) and paired_permutation_p(a, a) == 1.0
    # too many pairs to enumerate: 10,000 random flips from seed 0 by default, the same on every call
    rng = np.random.default_rng(3)
    x, y = rng.normal(0.1, 1.0, 40), rng.normal(0.0, 1.0, 40)
    p = paired_permutation_p(x, y)
    assert p == paired_permutation_p(x, y, flips=10_000, seed=0) and 0.0 < p < 1.0
    assert p != paired_permutation_p(x, y, flips=10_001) and p != paired_permutation_p(x, y, seed=1)


def test_paired_permutation_p_enumerates_every_flip_once_the_flips_reach_2_to_the_pairs():
    """Exact as soon as ``flips`` reaches 2^pairs, at exactly 2^pairs too and past scipy's default of 9,999
    resamples. The 6 pairs above with 64 flips: 8/64, as with 10,000. 14 pairs, 13 differences of +1 and one of -1
    (mean 12/14), with 2^14 flips: a pattern reaches a mean >= 12/14 when it flips nothing, only the -1, or the -1
    and one +1: 15 of 16,384, so p = 2 x 15 / 16,384. Random flips would give 2 (k + 1) / (flips + 1) instead."""
    from worldmodel.stats import paired_permutation_p

    a, b = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [0.5, 2.5, 2.0, 3.0, 4.5, 5.0]
    assert paired_permutation_p(a, b, flips=64) == pytest.approx(8 / 64, rel=1e-9)
    d = np.array([1.0] * 13 + [-1.0])
    assert paired_permutation_p(d, np.zeros(14), flips=2**14) == pytest.approx(30 / 2**14, rel=1e-9)


def test_the_sign_flip_p_of_no_mean_difference_is_1_and_its_ties_are_scipys():
    """Random flips (fewer than 2^pairs). Ten pairs differing by +1 and -1 in turn: mean difference 0, and a flip's
    mean is <= 0 (and >= 0) with probability (1 + 252/1024) / 2 = 0.62, so p = 2 x 0.62 is capped at 1. One pair
    differing by 1e-3 and 19 by 1e-12: every flip but the one that keeps all signs falls short of the observed mean
    by 1e-13 or more, far beyond the tie tolerance (100 eps x the mean, about 1e-18), and 1,000 draws of 2^20
    patterns miss that one, so p = 2 / 1,001. Differences in tenths: flips that cancel in decimal leave means a
    rounding error from the observed one, which scipy counts as ties, and so must the sign-flip p."""
    from scipy.stats import permutation_test

    from worldmodel.stats import paired_permutation_p

    assert paired_permutation_p([1.0, -1.0] * 5, np.zeros(10), flips=1000) == 1.0
    assert paired_permutation_p([1e-3] + [1e-12] * 19, np.zeros(20), flips=1000) == pytest.approx(2 / 1001)
    d = np.random.default_rng(0).integers(-3, 4, 30) / 10
    expected = permutation_test(
        (d,),
        lambda x, axis: np.mean(x, axis=axis),
        permutation_type="samples",
        n_resamples=1000,
        alternative="two-sided",
        vectorized=True,
        rng=np.random.default_rng(0),
    ).pvalue
    assert paired_permutation_p(d, np.zeros(30), flips=1000) == float(expected)


def test_rank_agreement_counts_the_pairs_a_scorer_orders_as_the_exact_costs_do_by_hand():
    """stats.rank_agreement, which the critics' pairwise order and Spearman rest on (counterfactual.pairwise_order,
    experiments/critic_vs_exact.py), on rows worked out by hand."""
    from worldmodel.stats import rank_agreement

    costs = np.array([[0.0, 1.0, 2.0], [0.0, 1.0, 2.0], [0.0, 1.0, 2.0], [5.0, 5.0, 5.0], [0.0, 0.0, 3.0]])
    scores = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0], [7.0, 7.0, 7.0], [1.0, 2.0, 3.0], [2.0, 1.0, 0.0]])
    a = rank_agreement(scores, costs)
    # row 0 orders all 3 pairs alike; row 1 none; a constant agrees on half of each; equal costs give no pair;
    # in row 4 the costs tie on the first pair (not counted) and the scores order the other two wrongly
    assert a["pairs"].tolist() == [3, 3, 3, 0, 2]
    assert a["agree"].tolist() == [3.0, 0.0, 1.5, 0.0, 0.0]
    assert a["spearman"][:3].tolist() == pytest.approx([1.0, -1.0, 0.0])
    assert math.isnan(a["spearman"][3])
    assert a["spearman"][4] == pytest.approx(-0.8660254)
    # costs closer than the tie share a rank and make no pair
    close = rank_agreement(np.array([[0.0, 1.0]]), np.array([[0.0, 5e-7]]))
    assert close["pairs"].tolist() == [0] and math.isnan(close["spearman"][0])
    assert rank_agreement(np.array([[0.0, 1.0]]), np.array([[0.0, 0.1]]), tie=0.2)["pairs"].tolist() == [0]
    assert rank_agreement(np.array([[0.0, 1.0]]), np.array([[0.0, 0.5]]), tie=0.5)["pairs"].tolist() == [0]
    assert a["pairs"].dtype.kind == "i"  # counts
    # unsigned inputs are read as floats: 0 - 2 is -2, not 254
    small = rank_agreement(np.array([[0, 1]], np.uint8), np.array([[0, 2]], np.uint8))
    assert small["agree"].tolist() == [1.0] and small["spearman"][0] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        rank_agreement(scores[:2], costs)  # a row without its scores
