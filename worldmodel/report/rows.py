"""The evaluation's rows: their columns, the policies' order and labels, the grid they cover, and their CSV
(plain or gzip) with the types restored."""

from __future__ import annotations

import csv
import functools
import gzip
import io
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from worldmodel.common import atomic_write_bytes, atomic_write_text

# ----------------------------------------------------------------------------- row schema
INT_COLUMNS = (
    "policy_seed",
    "scenario_id",
    "seed",
    "pedestrian_collision",
    "vehicle_collision",
    "static_collision",
    "lane_departure",
    "n_pedestrians_hit",
    "steps",
)
FLOAT_COLUMNS = (
    "ttc",
    "speed",
    "pedestrian_injury",
    "occupant_injury",
    "ego_occupant_injury",
    "speed_at_collision",
    "return_r1",
    "return_r2",
    "final_speed",
)
# Short SHA-256 of the VAE, LSTM and actor checkpoints that produced an agent's row (empty for scripted policies).
MODEL_COLUMNS = ("vae_sha", "rnn_sha", "actor_sha")
STR_COLUMNS = ("policy", "hazard", "end", *MODEL_COLUMNS)
# A row: which policy and scenario, the scenario's outcome (envs' info["outcome"]), the models behind the policy.
ROW_META = ("policy", "policy_seed", "scenario_id", "hazard", "ttc", "speed", "seed")
OUTCOME_COLUMNS = (
    "pedestrian_collision",
    "vehicle_collision",
    "static_collision",
    "lane_departure",
    "n_pedestrians_hit",
    "pedestrian_injury",
    "occupant_injury",
    "ego_occupant_injury",
    "speed_at_collision",
    "steps",
    "return_r1",
    "return_r2",
    # how the episode ended (envs' outcome "end": crash, left_scene, horizon) and the ego's speed then, m/s. Rows
    # written before these two columns lack them (read back: absent; written again: "" and nan); no table reads them
    "end",
    "final_speed",
)
COLUMNS = (*ROW_META, *OUTCOME_COLUMNS, *MODEL_COLUMNS)

POLICY_ORDER = ("braking", "agent_r1", "agent_r2", "oracle")
POLICY_LABELS = {
    "braking": "Straight-line braking",
    "agent_r1": "Brake&Steer, reward 1",
    "agent_r2": "Brake&Steer, reward 2",
    "agent_r1-privileged": "Brake&Steer on the true state (no camera), reward 1",
    "agent_r2-privileged": "Brake&Steer on the true state (no camera), reward 2",
    "agent_r2_chooser": "Chooser (brake, then one lane change), reward 2",
    "agent_r2_dag": "Cloned from the planner with 2 DAgger rounds, reward 2",
    "agent_r2_chooser_tele": "Chooser, frame band from a 30° second camera, reward 2",
    "agent_r2_counterfactual": "DDPG actor against counterfactual costs, reward 2",
    "agent_r2_counterfactual-privileged": "DDPG actor against counterfactual costs, on the true state, reward 2",
    "agent_r2_counterfactual_true_state": "DDPG actor against counterfactual costs, on the true state, reward 2",
    # settings of the counterfactual actor tried on the validation banks (docs/results/phase3/)
    "agent_r2_cfcons": "Counterfactual actor tried: pessimism 2, anchor 0.2",
    "agent_r2_cfbold": "Counterfactual actor tried: no pessimism, no anchor",
    "agent_r2_cfmore": "Counterfactual actor tried: 2,000 + 600 labelled episodes",
    "agent_r2_cfasym": "Counterfactual actor tried: its critic on the true state",
    "agent_r2_cfsearch": "Counterfactual actor tried: a search over 64 shifts",
    "agent_r2_cfasymsearch": "Counterfactual actor tried: critic on the true state and a search",
    "oracle": "Privileged planner (oracle)",
    "oracle_brake1": "Planner after 1 frame of straight braking (perception ceiling)",
    "oracle_brake2": "Planner after 2 frames of straight braking (perception ceiling)",
    "oracle_pixels1": "Planner once the hazard covers ≥ 1 px (camera cap)",
    "oracle_pixels3": "Planner once the hazard covers ≥ 3 px (camera cap)",
}

HAZARD_ORDER = ("pedestrian", "car", "both")


# ----------------------------------------------------------------------------- small helpers
def _key(x: Any) -> float:
    """Grid coordinate used for grouping (robust to float noise from CSV or arithmetic)."""
    return round(float(x), 6)


def _involves(hazard: str, who: str) -> bool:
    h = str(hazard).lower()
    if who == "all":
        return True
    if who == "pedestrian":
        return h == "both" or "pedestrian" in h
    if who == "car":
        return h == "both" or "car" in h or "vehicle" in h
    raise ValueError(f"unknown participant {who!r}")


def _ordered(values: Iterable[str], order: Sequence[str]) -> list[str]:
    values = set(values)
    head = [v for v in order if v in values]
    return head + sorted(values - set(head))


def policy_order(rows: Sequence[dict]) -> list[str]:
    """Policies in report order: braking, agent_r1, agent_r2, then the rest alphabetically."""
    return _ordered((r["policy"] for r in rows), POLICY_ORDER)


def policy_label(policy: str) -> str:
    return POLICY_LABELS.get(policy, policy)


def grid_of(rows: Sequence[dict]) -> dict[str, list]:
    """The hazards, TTCs and speeds present in ``rows`` (sorted; hazards in pedestrian, car, both order)."""
    return {
        "hazards": _ordered((str(r["hazard"]) for r in rows), HAZARD_ORDER),
        # each distinct value rounded once: a bank's thousands of rows hold a handful of TTCs and speeds
        "ttcs": sorted({_key(v) for v in {r["ttc"] for r in rows}}),
        "speeds": sorted({_key(v) for v in {r["speed"] for r in rows}}),
    }


def _values(rows: Sequence[dict], column: str) -> np.ndarray:
    vals = []
    for r in rows:
        # total_injury: everyone's severe-injury probabilities summed, which R2 penalises and the planner minimises
        v = r["pedestrian_injury"] + r["occupant_injury"] if column == "total_injury" else r.get(column)
        vals.append(np.nan if v is None else float(v))
    return np.asarray(vals, dtype=float)


def _mean(rows: Sequence[dict], column: str) -> float:
    """Mean of ``column`` ignoring NaN/None; NaN when there is nothing to average."""
    vals = _values(rows, column)
    vals = vals[np.isfinite(vals)]
    return float(vals.mean()) if vals.size else math.nan


def _json_number(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _fmt_ttc(t: float) -> str:
    return f"{t:.1f}" if float(t).is_integer() else f"{t:g}"


def _fmt_speed(s: float) -> str:
    return f"{s:g}"


# ----------------------------------------------------------------------------- CSV
def _csv_cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(int(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))  # shortest exact round-trip form; NaN -> "nan"
    return str(v)


@functools.lru_cache(maxsize=1 << 16)  # rows repeat their cells (a policy's name, "0", "nan"): parse each once
def _parse_cell(column: str, text: str) -> Any:
    if column in STR_COLUMNS:
        return text
    if column in FLOAT_COLUMNS:
        return math.nan if text == "" else float(text)
    if column in INT_COLUMNS:
        if text == "":
            return None
        try:
            return int(text)
        except ValueError:
            return int(float(text))
    # A column this module does not know: infer int, then float, else keep the string.
    if text == "":
        return None
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def write_results_csv(rows: Sequence[dict], path: str | Path) -> Path:
    """Write one line per row, known columns first, extra keys after them in sorted order. Atomic. A path ending
    in ``.gz`` is gzip-compressed, with no timestamp, so the same rows always give the same bytes."""
    extra = sorted({k for r in rows for k in r} - set(COLUMNS))
    fields = list(COLUMNS) + extra
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(fields)
    for r in rows:
        writer.writerow([_csv_cell(r.get(k)) for k in fields])
    path = Path(path)
    if path.suffix == ".gz":
        atomic_write_bytes(path, gzip.compress(buf.getvalue().encode(), compresslevel=9, mtime=0))
    else:
        atomic_write_text(path, buf.getvalue())
    return path


class MalformedRowsError(ValueError):
    """A results CSV that ``write_results_csv`` cannot have written: named by file and line, with the fix."""


def read_results_csv(path: str | Path) -> list[dict]:
    """Read a CSV written by ``write_results_csv`` (``.gz`` too) with its types restored (ints, floats incl. NaN,
    strs). A line with missing or extra cells, or a cell that is not its column's type, is a
    ``MalformedRowsError`` naming the file and the line."""
    path = Path(path)
    fix = "it was changed since the evaluation wrote it: restore it from git, or rerun the evaluation"
    with gzip.open(path, "rt", newline="") if path.suffix == ".gz" else open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        rows = []
        for line in reader:
            if None in line or None in line.values():
                raise MalformedRowsError(
                    f"{path}, line {reader.line_num}: {len(reader.fieldnames or [])} columns in the header, "
                    f"another number of cells here; {fix}"
                )
            try:
                rows.append({k: _parse_cell(k, v) for k, v in line.items()})
            except ValueError as err:
                raise MalformedRowsError(f"{path}, line {reader.line_num}: {err}; {fix}") from None
        return rows
