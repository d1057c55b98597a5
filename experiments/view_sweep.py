"""The camera's views compared (conf/view/; docs/results/views/): pixels on the pedestrian, perception, decisions.

    python -m experiments.view_sweep pixels     # the simulator: px on the hazard pedestrian per view (~10 s)
    python -m experiments.view_sweep figure     # from committed files only: the table and the figure

For each view, on the validation banks only:

* **pixels**: the mean number of pixels the hazard pedestrian covers in the onset frame of the validation bank's
  pedestrian scenarios at 30 m/s and TTC 1.0 s (bank 4711, 20 per cell, straight-line braking's first frame), and
  the share where it covers none; the narrow 30° second camera's frame beside them;
* **perception**: ``experiments/perception_probe``'s R² (a CNN on the raw frame band; its ``r2.json`` copied to
  ``docs/results/views/<view>/probe.json``);
* **decisions**: the chooser's and the counterfactual-cost actor's share of the achievable improvement on the
  validation banks 4711 and 4712 pooled, from the rows published in ``docs/results/views/<view>/`` (the paper's
  view: ``docs/results/phase3/``, the same quick-scale settings).

``figure`` writes ``docs/results/views/sweep.md`` and ``sweep.png``: share and pedestrian R² against the pixels.
The two-camera chooser (paper scale, bank 4711, ``docs/results/porav/``) is drawn as a reference point.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from worldmodel.report import published

REPO = Path(__file__).resolve().parent.parent
OUT = REPO / "docs/results/views"
VIEWS = ("paper64", "cover64", "pool64")
TELE_FOV = 30.0
CELL = (30.0, 1.0)  # m/s, s: where the paper's frame loses the pedestrian most
LEARNERS = {"agent_r2_chooser": "chooser", "agent_r2_counterfactual": "counterfactual actor"}
PROBE_FIELDS = ("pedestrian", "ped_dx", "ped_dy", "ped_vy", "car", "car_dx")


def rows_dir(view: str) -> Path:
    return REPO / "docs/results/phase3" if view == "paper64" else OUT / view


def measure_pixels(per_cell: int = 20) -> dict:
    """Per view (and the 30° camera): mean px of the hazard pedestrian at onset in the cell, and the share at 0."""
    from envs import scenario_bank
    from experiments.camera_pixels import pixels
    from worldmodel.recording import view_env

    entries = [
        e for e in scenario_bank(per_cell=per_cell, seed=4711) if e.hazard == "pedestrian" and (e.speed, e.ttc) == CELL
    ]
    out = {}
    for name, kwargs in [*((v, (90.0, view_env(v))) for v in VIEWS), ("tele30", (TELE_FOV, {}))]:
        onset = pixels(kwargs[0], entries, **kwargs[1])[CELL][:, 0]
        out[name] = {"px_mean": float(onset.mean()), "none_share": float((onset == 0).mean()), "scenarios": len(onset)}
    return {"cell": {"speed_mps": CELL[0], "ttc_s": CELL[1]}, "bank_seed": 4711, "per_cell": per_cell, "views": out}


def shares(directory: Path) -> dict[str, dict]:
    """Learner -> pooled share, interval and seeds, from the validation rows published in ``directory``."""
    if not any(directory.glob("validation*" + published.ROWS)):
        return {}
    _, _, pool = published.pooled_validation(directory)
    out = {}
    for policy, name in LEARNERS.items():
        if any(r["policy"] == policy for r in pool):
            f = published.bank_figures(pool, policy)
            out[name] = {"share": f["share"], "ci95": f["share_ci95"], "seeds": f["seeds"]}
    return out


def two_camera_reference() -> dict:
    """The two-camera chooser's share on the paper-scale validation bank (4711), from docs/results/porav/."""
    rows, _ = published.published(REPO / "docs/results/porav")["validation"]
    f = published.bank_figures(rows, "agent_r2_chooser_tele")
    return {"share": f["share"], "ci95": f["share_ci95"], "seeds": f["seeds"]}


def figure() -> str:
    pixels = json.loads((OUT / "pixels.json").read_text())["views"]
    probes = {v: json.loads(p.read_text()) for v in VIEWS if (p := OUT / v / "probe.json").exists()}
    if "paper64" not in probes and (old := OUT / "paper64_probe.json").exists():
        probes["paper64"] = json.loads(old.read_text())
    decided = {v: shares(rows_dir(v)) for v in VIEWS}
    tele = two_camera_reference()

    def cell(s: dict | None) -> str:
        if not s:
            return "–"
        lo, hi = s["ci95"]
        return f"{s['share']:.1f} [{lo:.1f}, {hi:.1f}] ({len(s['seeds'])} seed{'s' * (len(s['seeds']) > 1)})"

    head = ["view", "px on the pedestrian", "none at onset %", *(f"R² {f}" for f in PROBE_FIELDS)]
    head += [f"{name} share % [95 % CI]" for name in LEARNERS.values()]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for v in VIEWS:
        r2 = probes.get(v, {}).get("r2", {})
        lines.append(
            "| "
            + " | ".join(
                [
                    v,
                    f"{pixels[v]['px_mean']:.1f}",
                    f"{100 * pixels[v]['none_share']:.0f}",
                    *("–" if r2.get(f) is None else f"{r2[f]:.2f}" for f in PROBE_FIELDS),
                    *(cell(decided[v].get(name)) for name in LEARNERS.values()),
                ]
            )
            + " |"
        )
    t = pixels["tele30"]
    lines.append(
        f"| 30° second camera (reference) | {t['px_mean']:.1f} | {100 * t['none_share']:.0f} | "
        + " | ".join("–" for _ in PROBE_FIELDS)
        + f" | two-camera chooser, paper scale, bank 4711: {cell(tele)} | – |"
    )
    _plot(pixels, probes, decided, tele)
    return "\n".join(lines) + "\n"


def _plot(pixels: dict, probes: dict, decided: dict, tele: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_share, ax_r2) = plt.subplots(1, 2, figsize=(10, 4))
    markers = {"chooser": "o", "counterfactual actor": "s"}
    for v in VIEWS:
        x = pixels[v]["px_mean"]
        for name, s in decided[v].items():
            lo, hi = s["ci95"]
            ax_share.errorbar(
                x,
                s["share"],
                yerr=[[s["share"] - lo], [hi - s["share"]]],
                fmt=markers[name],
                capsize=3,
                label=f"{name}, {v}",
            )
        r2 = probes.get(v, {}).get("r2", {})
        for field, marker in (("pedestrian", "o"), ("ped_dx", "^")):
            if r2.get(field) is not None:
                ax_r2.plot(x, r2[field], marker, label=f"{field}, {v}")
    lo, hi = tele["ci95"]
    ax_share.errorbar(
        pixels["tele30"]["px_mean"],
        tele["share"],
        yerr=[[tele["share"] - lo], [hi - tele["share"]]],
        fmt="D",
        capsize=3,
        color="grey",
        label="two-camera chooser (paper scale)",
    )
    ax_share.axhline(0, color="k", lw=0.5)
    ax_share.set(
        xscale="symlog",
        xlabel=f"px on the pedestrian at {CELL[0]:g} m/s, TTC {CELL[1]:g} s (onset)",
        ylabel="share of the achievable improvement, %",
        title="Decisions (validation 4711+4712)",
    )
    ax_r2.axhline(0.8, color="grey", ls=":", lw=0.8)
    ax_r2.axhline(0.7, color="grey", ls="--", lw=0.8)
    ax_r2.set(
        xscale="symlog",
        ylim=(0, 1),
        xlabel=f"px on the pedestrian at {CELL[0]:g} m/s, TTC {CELL[1]:g} s",
        ylabel="R² on validation frames",
        title="Perception of the hazard pedestrian",
    )
    for ax in (ax_share, ax_r2):
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "sweep.png", dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["pixels", "figure"])
    args = parser.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    if args.what == "pixels":
        result = measure_pixels()
        (OUT / "pixels.json").write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps(result, indent=1))
    else:
        table = figure()
        (OUT / "sweep.md").write_text(
            "<!-- generated by `python -m experiments.view_sweep figure`; do not edit -->\n" + table
        )
        print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
