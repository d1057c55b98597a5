"""The Fig. 5-style heatmaps, drawn on an explicit Agg canvas (never ``pyplot``)."""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np

from .rows import _fmt_speed, _fmt_ttc, grid_of, policy_label, policy_order
from .summary import IMPROVEMENT_METRICS, absolute_grids, achievable_share_grids, improvement_grids


def _draw_heatmap(fig, ax, ttcs, speeds, arr, vmin, vmax, cmap, title):
    data = np.ma.masked_invalid(np.asarray(arr, dtype=float))
    cmap = _cmap(cmap)
    im = ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax, origin="lower", aspect="auto")
    ax.set_xticks(range(len(speeds)), [_fmt_speed(s) for s in speeds])
    ax.set_yticks(range(len(ttcs)), [_fmt_ttc(t) for t in ttcs])
    ax.set_xlabel("initial speed (m/s)")
    ax.set_ylabel("TTC (s)")
    ax.set_title(title, fontsize=9)
    span = max(abs(vmin), abs(vmax)) or 1.0
    digits = 1 if span >= 5 else 2 if span >= 0.5 else 3  # paper-scale injury risks are fractions of a point
    small = len(ttcs) * len(speeds) > 40
    for i in range(len(ttcs)):
        for j in range(len(speeds)):
            v = float(np.asarray(arr)[i, j])
            if math.isfinite(v):
                v = 0.0 if round(v, digits) == 0 else v  # no "-0.0" from float noise
                text, colour = f"{v:.{digits}f}", ("white" if abs(v) > 0.6 * span else "black")
            else:
                text, colour = "n/a", "0.35"
            ax.text(j, i, text, ha="center", va="center", fontsize=6 if small else 8, color=colour)
    fig.colorbar(im, ax=ax, fraction=0.08, pad=0.03)


def _cmap(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad="0.85")


def heatmaps_figure(rows: Sequence[dict], baseline: str = "braking"):
    """Fig. 5 of the paper: one row per non-baseline policy, columns (a)–(d), improvement over the baseline.

    Each panel is TTC (y) × initial speed (x), diverging colormap centred at 0 (red = better than the
    baseline), with a symmetric colour range shared down each column. With nothing to compare (only the
    baseline, or no baseline at all) it draws every present policy's absolute values in % instead and says so
    in the title. Returns a ``matplotlib.figure.Figure`` (Agg canvas, pyplot untouched).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = list(rows)
    policies = policy_order(rows)
    metrics = list(IMPROVEMENT_METRICS)
    shares: dict = {}
    if baseline in policies and len(policies) > 1:
        grids = improvement_grids(rows, baseline)
        panel_rows = [(p, grids[p]) for p in policies if p != baseline]
        mode = "improvement"
        shares = achievable_share_grids(rows, baseline)
    else:
        panel_rows = [(p, absolute_grids(rows, p)) for p in policies]
        mode = "absolute"
    n_cols = len(metrics) + (1 if shares else 0)

    n_rows = max(1, len(panel_rows))
    grid = grid_of(rows)
    row_h = 1.1 + 0.35 * max(3, len(grid["ttcs"]))  # titles and tick labels + the TTC cells
    fig = Figure(figsize=(4.2 * n_cols, row_h * n_rows + 0.5), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(n_rows, n_cols, squeeze=False, gridspec_kw=_panel_margins(fig, n_rows, n_cols))

    if not panel_rows:  # no rows at all
        for ax, m in zip(axes[0], metrics):
            ax.set_title(IMPROVEMENT_METRICS[m][0], fontsize=9)
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
        _suptitle(fig, "No evaluation rows to report")
        return fig

    for col, m in enumerate(metrics):
        finite = [np.abs(g[m][2][np.isfinite(g[m][2])]) for _, g in panel_rows]
        peak = max((float(f.max()) for f in finite if f.size), default=0.0)
        peak = peak if peak > 0 else 1.0
        for row, (policy, g) in enumerate(panel_rows):
            ttcs, speeds, arr = g[m]
            title = f"{policy_label(policy)}\n{IMPROVEMENT_METRICS[m][0]}"
            if mode == "improvement":
                _draw_heatmap(fig, axes[row, col], ttcs, speeds, arr, -peak, peak, "RdBu_r", title + " (pp)")
            else:
                _draw_heatmap(fig, axes[row, col], ttcs, speeds, arr, 0.0, peak, "Reds", title + " (%)")
    for row, (policy, _) in enumerate(panel_rows if shares else []):
        # Fixed range: 100 % = as good as the planner; values past +-100 keep their number, saturate in colour.
        _draw_heatmap(
            fig,
            axes[row, -1],
            *shares[policy],
            -100.0,
            100.0,
            "RdBu_r",
            f"{policy_label(policy)}\n(e) share of achievable improvement,\ntotal injury risk (%)",
        )
    if mode == "improvement":
        _suptitle(
            fig,
            f"Percentage-point improvement over {policy_label(baseline).lower()} "
            "(baseline − policy; red/positive = better)",
        )
    else:
        who = ", ".join(policy_label(p) for p, _ in panel_rows)
        why = "only the baseline was evaluated" if baseline in policies else f"baseline {baseline!r} missing"
        _suptitle(fig, f"No policy to compare ({why}): absolute values (%) for {who}")
    return fig


# Fixed margins around the panels, in inches: a layout engine would measure every label of every panel on each draw
# (twice the drawing time), and these labels are the same few lines at the same sizes in every figure.
TITLE_IN = 0.62  # a panel's title: up to three lines at 9 pt
XLABEL_IN = 0.5  # tick labels and the x label under a panel
YLABEL_IN = 0.65  # the y label and its tick labels, left of a panel
COLORBAR_IN = 0.45  # a panel's colour bar's tick labels, right of the bar that the panel's own width gives up
SUPTITLE_IN = 0.35  # the figure's title line above them all


def _panel_margins(fig, n_rows: int, n_cols: int) -> dict:
    """GridSpec keywords that leave the fixed margins above around a grid of panels on ``fig``."""
    width, height = fig.get_size_inches()
    axes_w = (width - YLABEL_IN * n_cols - COLORBAR_IN * n_cols) / n_cols
    axes_h = (height - SUPTITLE_IN - (TITLE_IN + XLABEL_IN) * n_rows) / n_rows
    return {
        "left": YLABEL_IN / width,
        "right": 1 - COLORBAR_IN / width,
        "top": 1 - (SUPTITLE_IN + TITLE_IN) / height,
        "bottom": XLABEL_IN / height,
        "wspace": (YLABEL_IN + COLORBAR_IN) / axes_w,
        "hspace": (TITLE_IN + XLABEL_IN) / axes_h,
    }


def _suptitle(fig, text: str) -> None:
    """The figure's title, a fixed distance below its top edge whatever the figure's height."""
    fig.suptitle(text, y=1 - 0.08 / fig.get_figheight())


def _render_rgb(fig) -> np.ndarray:
    """Draw ``fig`` once on its Agg canvas and return the pixels as an (H, W, 3) uint8 array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.array(canvas.buffer_rgba())[..., :3]


def _png_bytes(rgb: np.ndarray, dpi: float) -> bytes:
    from matplotlib.image import imsave

    buf = io.BytesIO()
    imsave(buf, rgb, format="png", dpi=dpi)
    return buf.getvalue()
