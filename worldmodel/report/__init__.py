"""Reports of an evaluation bank: CSV, JSON summary, the paper's Tables I–III and a Fig. 5-style heatmap.

Input is one *row* (a dict) per scenario and policy, as produced by the evaluation stage::

    policy, scenario_id, hazard, ttc, speed, seed,
    pedestrian_collision, vehicle_collision, static_collision, lane_departure,   # 0/1
    n_pedestrians_hit, pedestrian_injury, occupant_injury, ego_occupant_injury,
    speed_at_collision (NaN if no collision), steps, return_r1, return_r2

Any subset of the grid hazard × TTC × speed and any set of policies is accepted; the grid is read off the rows.

Choices made here (the paper is silent on them):

* A cell is (hazard, TTC, speed). A metric of a cell is the plain mean over that cell's scenarios.
* "Hazard involves a pedestrian" means hazard ``pedestrian`` or ``both``; "involves a car" means ``car`` or ``both``.
  Pedestrian metrics (Table I, Table III, Fig. 5 a/b) average over pedestrian-involving scenarios only, so a
  car-only scenario, where no pedestrian is in danger, does not dilute them. Car-collision rate (Fig. 5 c) averages
  over car-involving scenarios. Occupant injury (Table II, Fig. 5 d) averages over *all* scenarios: swerving
  away from a pedestrian into a pole hurts the occupants too and must count against the policy.
* Improvement is ``baseline − policy`` in percentage points (×100), so positive means better than straight-line
  braking, as in the paper's Fig. 5 ("the more red, the lower the rate compared to braking").  Because every
  policy runs the *same* seeded scenarios, the difference of means equals the mean paired difference.
* Figures are built on ``matplotlib.figure.Figure`` with an explicit Agg canvas and never through ``pyplot``, so
  importing or calling this module never switches the backend of a notebook or opens a window.
* Every file is written atomically (temporary file + ``os.replace``), so a crash never leaves half a report.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from worldmodel.common import atomic_write_bytes, atomic_write_text

from .figures import _png_bytes, _render_rgb, heatmaps_figure
from .rows import (
    COLUMNS,
    FLOAT_COLUMNS,
    INT_COLUMNS,
    MODEL_COLUMNS,
    OUTCOME_COLUMNS,
    POLICY_LABELS,
    POLICY_ORDER,
    STR_COLUMNS,
    MalformedRowsError,
    _mean,
    grid_of,
    policy_label,
    policy_order,
    read_results_csv,
    write_results_csv,
)
from .summary import (
    CEILING,
    MIN_ACHIEVABLE_GAIN,
    achievable_share_grids,
    cells_above_baseline,
    improvement_grids,
    overall_achievable_share,
    paired_bootstrap,
    policy_seeds,
    seed_spread,
    share_of_gain,
    summarize,
)
from .tables import MISSING, _fmt, _md_row, tables_markdown

__all__ = [
    "CEILING",
    "COLUMNS",
    "FLOAT_COLUMNS",
    "INT_COLUMNS",
    "MIN_ACHIEVABLE_GAIN",
    "MISSING",
    "MODEL_COLUMNS",
    "OUTCOME_COLUMNS",
    "POLICY_LABELS",
    "POLICY_ORDER",
    "STR_COLUMNS",
    "_fmt",
    "_md_row",
    "_mean",
    "share_of_gain",
    "achievable_share_grids",
    "cells_above_baseline",
    "grid_of",
    "heatmaps_figure",
    "improvement_grids",
    "overall_achievable_share",
    "paired_bootstrap",
    "policy_label",
    "policy_order",
    "policy_seeds",
    "read_results_csv",
    "MalformedRowsError",
    "seed_spread",
    "summarize",
    "tables_markdown",
    "render_report",
    "write_results_csv",
]


def render_report(
    rows: Sequence[dict], out_dir: str | Path, tb_writer=None, step: int = 0, baseline: str = "braking"
) -> dict:
    """Write ``tables.md`` and ``heatmaps.png`` into ``out_dir`` (atomically); return the summary, which the caller
    writes (``summary.json`` marks an evaluation complete, so it comes last).

    With a ``torch.utils.tensorboard.SummaryWriter`` it also logs the heatmap figure as an image
    (``report/heatmaps``, the same pixels ``add_figure`` would log, from a single draw), the
    tables as text (``report/tables``) and each policy's overall rates as scalars (``report/<policy>/<metric>``).
    """
    rows = list(rows)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summarize(rows, baseline=baseline)
    json.dumps(summary, allow_nan=False)  # a NaN in the summary is a bug upstream: refuse it before writing anything
    tables = tables_markdown(rows)
    fig = heatmaps_figure(rows, baseline=baseline)
    atomic_write_text(out_dir / "tables.md", tables)
    rgb = _render_rgb(fig)  # drawn once (the slow part), reused for the PNG and TensorBoard
    atomic_write_bytes(out_dir / "heatmaps.png", _png_bytes(rgb, fig.dpi))
    if tb_writer is not None:
        # Exactly what SummaryWriter.add_figure logs (canvas pixels, RGB, as an image), minus a second draw.
        tb_writer.add_image("report/heatmaps", rgb, global_step=step, dataformats="HWC")
        tb_writer.add_text("report/tables", tables, global_step=step)
        for policy, entry in summary["policies"].items():
            for metric in (
                "pedestrian_collision_rate",
                "vehicle_collision_rate",
                "static_collision_rate",
                "pedestrian_severe_injury",
                "occupant_severe_injury",
            ):
                value = entry["overall"][metric]
                if value is not None:
                    tb_writer.add_scalar(f"report/{policy}/{metric}", value, global_step=step)
        tb_writer.flush()
    return summary
