"""The Euro NCAP bank's summary, tables and figure (``python -m worldmodel.ncap``), from its rows alone, so that
``worldmodel.report recheck`` renders committed NCAP runs again without the stage."""

from __future__ import annotations

import numpy as np


def _key(row) -> str:
    return row["policy"] if not row["policy"].startswith("agent_") else f"{row['policy']}/seed{row['policy_seed']}"


def _label(row) -> str:
    return f"{row['test']} {row['variant']}".strip()


def _mean(values) -> float | None:
    values = list(values)
    return float(np.mean(values)) if values else None


def pct(share: float | None) -> float | None:
    return None if share is None else 100 * share


def summarise(rows: list[dict]) -> dict:
    """Per policy: the pedestrian tests' avoidance, 2015 aim and impact speed; the car tests' avoidance, points and
    relative impact speed; collisions with anything else."""
    out = {"policies": {}}
    for key in dict.fromkeys(_key(r) for r in rows):
        mine = [r for r in rows if _key(r) == key]
        ped = [r for r in mine if r["kind"] == "pedestrian"]
        car = [r for r in mine if r["kind"] == "car"]
        out["policies"][key] = {
            "family": mine[0]["family"],
            "pedestrian_runs": len(ped),
            "pedestrian_avoided_pct": pct(_mean(r["avoided"] for r in ped)),
            "aim_met_pct": pct(_mean(r["verdict"] == "pass" for r in ped)),
            "pedestrian_impact_kmh": _mean(r["impact_kmh"] for r in ped if not r["avoided"]),
            "car_runs": len(car),
            "car_avoided_pct": pct(_mean(r["avoided"] for r in car)),
            "car_points_pct": pct(_mean(r["points"] for r in car)),
            "car_impact_kmh": _mean(r["impact_kmh"] for r in car if not r["avoided"]),
            "other_collisions": int(sum(r["other_collision"] for r in mine)),
            "clean_pct": pct(_mean(r["avoided"] and not r["other_collision"] for r in mine)),
        }
    return out


def _fmt(value, digits: int = 0) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def tables(rows: list[dict], summary: dict) -> str:
    lines = [
        "# Euro NCAP AEB tests (approximate: our reading of the protocol, envs/ncap.py)",
        "",
        f"Paper-family policies take over at TTC {summary['takeover_ttc_s']:g} s (the car holds its speed until "
        "then); the peers' policies drive from the test's start. Pedestrian aim (Euro NCAP 2015): avoid up to "
        "40 km/h, hit below 40 km/h from 40 to 60 km/h. Car points: 1 for avoidance, else by the relative impact "
        "speed (< 5 km/h 1, < 15 0.75, < 30 0.5, < 40 0.25; none at 20 km/h and below), confirmed for "
        "CCRs at 50 km/h and at 20 km/h and below, approximate elsewhere. n/a: the policy does not run these "
        "tests. Other collisions: runs that also hit a parked car, a pole or the street; clean runs: the target "
        "avoided and nothing else hit, over every test the policy ran.",
        "",
        "| policy | family | pedestrian avoided % | aim met % | mean impact, km/h | car avoided % | car points % "
        "| mean relative impact, km/h | other collisions | clean runs % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, s in summary["policies"].items():
        lines.append(
            f"| {key} | {s['family']} | {_fmt(s['pedestrian_avoided_pct'])} | {_fmt(s['aim_met_pct'])} | "
            f"{_fmt(s['pedestrian_impact_kmh'], 1) if s['pedestrian_runs'] else 'n/a'} | "
            f"{_fmt(s['car_avoided_pct'])} | {_fmt(s['car_points_pct'])} | "
            f"{_fmt(s['car_impact_kmh'], 1) if s['car_runs'] else 'n/a'} | {s['other_collisions']} | "
            f"{_fmt(s['clean_pct'])} |"
        )
    lines += [
        "",
        "## Per test and speed: ✓ avoided, else the impact speed in km/h (relative for the car tests; ✗: the "
        "pedestrian aim is missed; *: the car also hit something else)",
        "",
    ]
    for key in summary["policies"]:
        mine = [r for r in rows if _key(r) == key]
        lines += [f"### {key}", ""]
        for kind in ("pedestrian", "car"):
            part = [r for r in mine if r["kind"] == kind]
            if not part:
                continue
            speeds = sorted({r["speed_kmh"] for r in part})
            lines += ["| test | " + " | ".join(f"{v:g}" for v in speeds) + " |", "|---|" + "---:|" * len(speeds)]
            for label in dict.fromkeys(_label(r) for r in part):
                cells = []
                for v in speeds:
                    r = next((r for r in part if _label(r) == label and r["speed_kmh"] == v), None)
                    if r is None:
                        cells.append("")
                        continue
                    cell = "✓" if r["avoided"] else f"{r['impact_kmh']:.0f}"
                    cell += "*" if r["other_collision"] else ""
                    cells.append(cell + (" ✗" if r["verdict"] == "fail" else ""))
                lines.append(f"| {label} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def figure(rows: list[dict], path) -> None:
    """At a glance: per policy, the share of pedestrian and car tests avoided and the car points, as bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = summarise(rows)["policies"]
    keys = list(summary)
    bars = (
        ("pedestrian_avoided_pct", "pedestrian tests avoided"),
        ("car_avoided_pct", "car tests avoided"),
        ("car_points_pct", "car points (approx.)"),
        ("clean_pct", "clean runs: nothing hit at all"),
    )
    fig, ax = plt.subplots(figsize=(max(7.0, 0.75 * len(keys) + 2.5), 4.2))
    width = 0.8 / len(bars)
    x = np.arange(len(keys))
    for k, (field, label) in enumerate(bars):
        values = [summary[key][field] for key in keys]
        at = x + (k - (len(bars) - 1) / 2) * width
        ax.bar(at, [np.nan if v is None else v for v in values], width, label=label)
        for xi, v in zip(at, values, strict=True):
            if v is None:
                ax.text(xi, 2, "n/a", ha="center", fontsize=6, rotation=90)
    ax.set_xticks(x, keys, rotation=35, ha="right", fontsize=7)
    ax.set_ylim(0, 105)
    ax.set_ylabel("%")
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.06), ncol=len(bars), frameon=False)
    ax.set_title("Euro NCAP AEB tests (approximate), every policy: higher is better", fontsize=10, pad=24)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
