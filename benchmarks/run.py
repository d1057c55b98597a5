"""Run the benchmarks and write ``benchmarks/RESULTS.md`` from every JSON in ``benchmarks/results/``.

    python -m benchmarks.run                      # all benchmarks at full size, then the report (make bench)
    python -m benchmarks.run --quick              # smaller sizes: minutes instead of tens of minutes
    python -m benchmarks.run --only decision      # one benchmark (repeatable: --only env --only stages)
    python -m benchmarks.run --report-only        # no measuring: regenerate RESULTS.md from the JSONs

``--tiny`` passes seconds-long sizes, to check that the scripts work; its numbers are not measurements and
RESULTS.md says so. Targets are docs/design.md §7.

A section of RESULTS.md written by hand (an A/B timing, a measurement no JSON holds) carries the line ``BY_HAND``
right under its ``## `` heading; rewriting the file keeps every such section, in its order, after the generated ones.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from .common import RESULTS_DIR, machine

REPORT = Path(__file__).resolve().parent / "RESULTS.md"
ORDER = ("env", "stages", "decision")
BY_HAND = "<!-- written by hand: benchmarks.run keeps this section -->"

# Sizes passed to each benchmark's main(argv) per preset ("full" = the benchmark's own defaults).
PRESETS = {
    "full": {"env": [], "stages": [], "decision": []},
    "quick": {
        "env": ["--steps", "1000", "--resets", "2000", "--per-cell", "5"],
        "stages": ["--episodes", "8", "--max-episode-s", "5"],
        "decision": ["--decisions", "1000", "--warmup", "100"],
    },
    "tiny": {
        "env": ["--steps", "200", "--resets", "100", "--per-cell", "1"],
        "stages": ["--tiny"],
        "decision": ["--tiny"],
    },
}

# docs/design.md §7.
TARGET_STEPS_CAMERA_ON = 500.0
TARGET_STEPS_CAMERA_OFF = 5000.0
TARGET_RESET_MS = 10.0
TARGET_RESETS = 10_000
FLAT_MB = 2.0  # our reading of "memory flat": RSS growth over the resets below this
TARGET_DECISION_P50_MS = 1.0
TARGET_PEAK_MB = 4096.0
PAPER_FRAMES = 200_000  # paper-scale pipeline: 200k frames, VAE 2 epochs, the whole pipeline <= 2 h
PAPER_VAE_EPOCHS = 2
PAPER_TRAIN_SHARE = 0.9  # conf/base.yaml collect.validation_fraction = 0.1
PIPELINE_BUDGET_S = 2 * 3600.0


# ----------------------------------------------------------------------------- running
def run_benchmark(name: str, argv: list[str], preset: str) -> None:
    from importlib import import_module

    module = import_module(f"benchmarks.bench_{name}")
    print(f"\n=== bench_{name} {' '.join(argv)}", flush=True)
    t0 = time.perf_counter()
    module.main(list(argv))
    # Record how the file was made (bench_env does not store its own arguments).
    path = RESULTS_DIR / f"{name}.json"
    if path.exists():
        data = json.loads(path.read_text())
        data["command"] = " ".join([f"python -m benchmarks.bench_{name}", *map(shlex.quote, argv)])
        data["preset"] = preset
        data["bench_wall_s"] = round(time.perf_counter() - t0, 1)
        path.write_text(json.dumps(data, indent=2) + "\n")


# ----------------------------------------------------------------------------- formatting
def fmt(x, digits: int = 1) -> str:
    if x is None:
        return "–"
    if isinstance(x, (int,)) and not isinstance(x, bool):
        return f"{x:,}"
    x = float(x)
    if abs(x) >= 1000:
        return f"{x:,.0f}"
    if abs(x) >= 100:
        return f"{x:.{max(digits - 1, 0)}f}" if digits > 1 else f"{x:.0f}"
    return f"{x:.{digits}f}"


def at_least(value, target) -> str:
    if value is None:
        return "not measured"
    if value >= target:
        return f"**met** ({value / target:.1f}× the target)"
    if value <= 0:
        return "**missed**"
    return f"**missed**: {target / value:.1f}× short ({100 * (value / target - 1):+.0f}%)"


def at_most(value, target, unit: str = "") -> str:
    if value is None:
        return "not measured"
    if value <= target:
        return f"**met** ({100 * (1 - value / target):.0f}% under)"
    return f"**missed** by {fmt(value - target, 2)}{unit} ({100 * (value / target - 1):+.0f}%)"


def table(header: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def machine_line(m: dict) -> str:
    if not m:
        return "unknown machine"
    parts = [
        f"{m.get('cpu', '?')}, {m.get('cpus', '?')} logical CPUs",
        m.get("platform", "?"),
        f"Python {m.get('python', '?')}",
        f"numpy {m.get('numpy', '?')}",
    ]
    if "torch" in m:
        parts.append(f"torch {m['torch']}")
    return "; ".join(parts)


def provenance(data: dict) -> list[str]:
    lines = [
        f"Measured with `{data.get('command', 'command not recorded')}`"
        + (f" (preset `{data['preset']}`)" if data.get("preset") else "")
        + (f", {data['bench_wall_s']} s" if data.get("bench_wall_s") else "")
        + "."
    ]
    if data.get("loadavg_at_start"):
        lines.append(
            f"Load average at start: {', '.join(str(x) for x in data['loadavg_at_start'])} "
            f"(on a shared machine, other work slows every number down)."
        )
    if is_tiny(data):
        lines[:0] = [
            "> **Tiny run: a check that the benchmark works, NOT a measurement.** Sizes are seconds-long; "
            "rerun with `python -m benchmarks.run` for real numbers.",
            "",
        ]
    return lines


def is_tiny(data: dict) -> bool:
    return bool(data.get("tiny")) or data.get("preset") == "tiny"


def add_summary(summary: list, data: dict, row: list) -> None:
    """A row of the summary table; numbers from a tiny run are labelled as such."""
    if is_tiny(data):
        row = [row[0], f"{row[1]} (tiny run)", row[2], f"{row[3]} (tiny run: not a measurement)"]
    summary.append(row)


# ----------------------------------------------------------------------------- sections
def section_env(d: dict, summary: list) -> str:
    out = ["## Simulator (`env.json`)", "", *provenance(d)]
    if "command" not in d:
        sizes = [
            f"{d[k]['resets']:,} resets with camera {k.rsplit('_', 1)[1]}"
            for k in ("reset_camera_on", "reset_camera_off")
            if k in d
        ]
        if "hazard_visible_at_onset" in d:
            sizes.append(f"{d['hazard_visible_at_onset'].get('per_cell', '?')} scenario(s) per visibility cell")
        out.append(f"Sizes (read from the file; step counts not recorded): {', '.join(sizes)}.")
    out.append("")
    on, off = d.get("steps_per_s_camera_on"), d.get("steps_per_s_camera_off")
    rows = [
        [
            "env steps/s, camera on, one process",
            fmt(on),
            f"≥ {fmt(TARGET_STEPS_CAMERA_ON)}",
            at_least(on, TARGET_STEPS_CAMERA_ON),
        ],
        [
            "env steps/s, camera off",
            fmt(off),
            f"≥ {fmt(TARGET_STEPS_CAMERA_OFF)}",
            at_least(off, TARGET_STEPS_CAMERA_OFF),
        ],
    ]
    for row in rows:
        add_summary(summary, d, row)
    tele = d.get("steps_per_s_camera_on_tele")
    if tele is not None:  # no target: an option, a second render per step
        rows.append(
            ["env steps/s, camera on, with the 30° second camera (`env.tele_fov_deg=30`)", fmt(tele), "–", "no target"]
        )
    kim = d.get("steps_per_s_camera_on_kim")
    if kim is not None:  # no target: a peer family's junction, drawn per pixel like the street
        rows.append(["env steps/s, camera on, family kim (the junction, 0.1 s steps)", fmt(kim), "–", "no target"])
    for key, label in (("reset_camera_on", "camera on"), ("reset_camera_off", "camera off")):
        r = d.get(key)
        if not r:
            continue
        p50 = r.get("reset_ms_p50")
        rows.append(
            [
                f"reset cost, {label}, p50 (p95)",
                f"{fmt(p50, 2)} ms ({fmt(r.get('reset_ms_p95'), 2)} ms)",
                f"≤ {fmt(TARGET_RESET_MS)} ms",
                at_most(p50, TARGET_RESET_MS, " ms"),
            ]
        )
        add_summary(
            summary,
            d,
            [
                f"reset cost p50, {label}",
                f"{fmt(p50, 2)} ms",
                f"≤ {fmt(TARGET_RESET_MS)} ms",
                at_most(p50, TARGET_RESET_MS, " ms"),
            ],
        )
        n, growth = r.get("resets", 0), r.get("rss_growth_mb")
        if growth is None:
            status = "not measured"
        elif growth > FLAT_MB:
            status = f"**missed**: grew {fmt(growth, 2)} MB ({1024 * growth / max(n, 1):.2f} KB per reset)"
        elif n >= TARGET_RESETS:
            status = "**met**"
        else:
            status = f"flat so far, **inconclusive**: {n:,} of {TARGET_RESETS:,} resets"
        measured = (
            f"{fmt(growth, 2)} MB over {n:,} resets ({fmt(r.get('rss_before_mb'))} → {fmt(r.get('rss_after_mb'))} MB)"
        )
        rows.append(
            [f"RSS growth over resets, {label}", measured, f"flat (< {FLAT_MB:g} MB) over {TARGET_RESETS:,}", status]
        )
        add_summary(
            summary,
            d,
            [
                f"memory flat over resets, {label}",
                f"{fmt(growth, 2)} MB / {n:,} resets",
                f"flat over {TARGET_RESETS:,}",
                status,
            ],
        )
    out += [table(["what", "measured", "target", "status"], rows), ""]
    vis = d.get("hazard_visible_at_onset")
    if vis:
        out += [visibility_tables(vis), ""]
    return "\n".join(out)


def visibility_tables(vis: dict) -> str:
    cells = vis.get("cells", {})
    kinds: dict[str, dict[tuple[float, float], float]] = {}
    for key, frac in cells.items():
        hazard, ttc, speed = key.split("|")
        kinds.setdefault(hazard, {})[(float(ttc), float(speed))] = frac
    out = [
        "### Hazard visible at onset",
        "",
        f"Share of bank-2018 scenarios whose hazard covers at least one pixel of the first (onset) frame, "
        f"field of view {fmt(vis.get('fov_deg'), 0)}°, {vis.get('per_cell', '?')} scenario(s) per cell; "
        f"overall **{100 * vis.get('overall', float('nan')):.0f}%**. Rows: TTC (s); columns: ego speed (m/s). "
        "No target in docs/design.md; a hazard the camera cannot see at onset cannot be avoided by a vision policy.",
        "",
    ]
    for hazard, grid in kinds.items():
        ttcs = sorted({t for t, _ in grid})
        speeds = sorted({s for _, s in grid})
        rows = [[fmt(t, 2)] + [f"{100 * grid[(t, s)]:.0f}%" if (t, s) in grid else "–" for s in speeds] for t in ttcs]
        mean = 100 * sum(grid.values()) / len(grid)
        out += [
            f"**{hazard}** (mean {mean:.0f}%)",
            "",
            table(["TTC \\ speed"] + [f"{s:g} m/s" for s in speeds], rows),
            "",
        ]
    return "\n".join(out)


def section_stages(d: dict, summary: list) -> str:
    p = d.get("params", {})
    out = [
        "## Phase 0 collection and phase 1 VAE (`stages.json`)",
        "",
        *provenance(d),
        "",
        f"Each run is the real stage command in a fresh subprocess at `scale=smoke` with "
        f"{p.get('episodes', '?')} episodes of at most {p.get('max_episode_s', '?')} s, VAE "
        f"{p.get('vae_epochs', '?')} epoch(s) at batch {p.get('vae_batch_size', '?')}. *frames/s (wall)* divides by "
        "the whole subprocess time (interpreter, imports, Hydra, pool start-up, validation); *in-stage* is the "
        "stage's own figure (collection: frames / collection loop; VAE: `metrics.json` `train_frames_per_s`, "
        "which still includes validation). *max RSS* is the largest single process (`wait4` ru_maxrss); *tree peak* "
        "is the largest sum over the process and its workers (psutil, sampled every 0.1 s).",
        "",
    ]
    rows = []
    c = d.get("collect", {})
    v = d.get("vae", {})
    runs = [(f"collect, {r.get('num_workers')} worker(s)", r) for k, r in c.items() if k.startswith("workers_")]
    runs += [(f"VAE, {r.get('threads')} thread(s)", r) for k, r in v.items() if k.startswith("threads_")]
    for label, r in runs:
        frames = r.get("frames", r.get("train_frames"))
        rows.append(
            [
                label,
                fmt(frames),
                fmt(r.get("wall_s")),
                fmt(r.get("frames_per_s")),
                fmt(r.get("frames_per_s_in_stage")),
                fmt(r.get("max_rss_mb"), 0),
                fmt(r.get("tree_peak_rss_mb"), 0),
                at_most(r.get("tree_peak_rss_mb"), TARGET_PEAK_MB, " MB"),
            ]
        )
    out += [
        table(
            [
                "run",
                "frames",
                "wall s",
                "frames/s (wall)",
                "frames/s (in-stage)",
                "max RSS MB",
                "tree peak MB",
                "peak ≤ 4 GB",
            ],
            rows,
        ),
        "",
    ]
    if "speedup_2_vs_1" in c or "speedup_2_vs_1" in v:
        out += [
            f"Speed-up of 2 over 1: collection {fmt(c.get('speedup_2_vs_1'), 2)}×, VAE "
            f"{fmt(v.get('speedup_2_vs_1'), 2)}× (2 cores; ideal 2×).",
            "",
        ]
    frames = sum(r.get("frames", 0) for k, r in c.items() if k.startswith("workers_")) // max(
        1, len([k for k in c if k.startswith("workers_")])
    )
    out += [
        f"Peak memory is measured at this benchmark's size ({fmt(frames)} frames per collection), not at "
        f"paper scale ({fmt(PAPER_FRAMES)} frames): the ≤ 4 GB target holds there only as far as the stages' "
        "memory does not grow with the dataset (collection keeps one shard of episodes per worker in memory; "
        "the VAE streams its batches).",
        "",
    ]
    for stage, peak in d.get("peak_tree_rss_mb", {}).items():
        add_summary(
            summary,
            d,
            [
                f"peak memory, {stage} (process tree, bench size)",
                f"{fmt(peak, 0)} MB",
                "≤ 4,096 MB",
                at_most(peak, TARGET_PEAK_MB, " MB"),
            ],
        )

    # Projection to paper scale from the best in-stage rates: at paper scale start-up is a small share, which the
    # in-stage figures leave out (the VAE's still includes its validation passes).
    def best(runs: dict, prefix: str) -> float:
        return max(
            (
                r.get("frames_per_s_in_stage") or r.get("frames_per_s") or 0
                for k, r in runs.items()
                if k.startswith(prefix)
            ),
            default=0,
        )

    best_c, best_v = best(c, "workers_"), best(v, "threads_")
    if is_tiny(d):
        out += ["No projection to paper scale from a tiny run (start-up and validation dominate it).", ""]
    elif best_c and best_v:
        t_c = PAPER_FRAMES / best_c
        t_v = PAPER_VAE_EPOCHS * PAPER_TRAIN_SHARE * PAPER_FRAMES / best_v
        share = 100 * (t_c + t_v) / PIPELINE_BUDGET_S
        out += [
            "### Projection to paper scale",
            "",
            table(
                ["stage", "work", "best rate (frames/s, in-stage)", "projected wall"],
                [
                    ["collect", f"{fmt(PAPER_FRAMES)} frames", fmt(best_c), f"{t_c / 60:.0f} min"],
                    [
                        "VAE",
                        f"{PAPER_VAE_EPOCHS} epochs × {fmt(int(PAPER_TRAIN_SHARE * PAPER_FRAMES))} train frames",
                        fmt(best_v),
                        f"{t_v / 60:.0f} min",
                    ],
                ],
            ),
            "",
            f"Phases 0 and 1 together: **{(t_c + t_v) / 60:.0f} min, {share:.0f}% of the 2 h budget** for the "
            "whole "
            "paper-scale pipeline (LSTM, DDPG and evaluation still to come). A linear extrapolation from a short "
            "run; not a measurement.",
            "",
        ]
        add_summary(
            summary,
            d,
            [
                "phases 0+1 at paper scale (projected)",
                f"{(t_c + t_v) / 60:.0f} min",
                "whole pipeline ≤ 120 min",
                f"{share:.0f}% of the budget",
            ],
        )
    return "\n".join(out)


def section_decision(d: dict, summary: list) -> str:
    out = ["## Decision latency (`decision.json`)", "", *provenance(d), ""]
    m, p = d.get("models", {}), d.get("params", {})
    params = m.get("parameters", {})
    out += [
        f"`LearnedPolicy.act(obs, info)` on real rendered frames ({p.get('distinct_frames', '?')} frames from "
        f"{p.get('scenarios', '?')} scenarios), batch 1, {d.get('torch_threads', '?')} torch thread(s); "
        f"{fmt(p.get('decisions'))} decisions after {fmt(p.get('warmup'))} warm-up. Untrained models of the real "
        f"sizes: VAE encoder latent {m.get('latent_dim', '?')} ({fmt(params.get('vae_encoder'))} parameters), "
        f"LSTM {m.get('lstm_hidden', '?')} with an MDN head of {m.get('mdn_gaussians', '?')} Gaussians "
        f"({fmt(params.get('rnn'))}), actor {'-'.join(map(str, m.get('actor_hidden', [])))} "
        f"({fmt(params.get('actor'))}).",
        "",
    ]
    t = d.get("decision", {})
    p50 = t.get("p50_ms")
    out += [
        table(
            ["what", "p50", "p95", "p99", "mean", "target", "status"],
            [
                [
                    "class map → action",
                    f"{fmt(p50, 3)} ms",
                    f"{fmt(t.get('p95_ms'), 3)} ms",
                    f"{fmt(t.get('p99_ms'), 3)} ms",
                    f"{fmt(t.get('mean_ms'), 3)} ms",
                    f"p50 ≤ {fmt(TARGET_DECISION_P50_MS)} ms",
                    at_most(p50, TARGET_DECISION_P50_MS, " ms"),
                ]
            ],
        ),
        "",
    ]
    add_summary(
        summary,
        d,
        [
            "decision latency p50 (1 thread)",
            f"{fmt(p50, 3)} ms",
            f"≤ {fmt(TARGET_DECISION_P50_MS)} ms",
            at_most(p50, TARGET_DECISION_P50_MS, " ms"),
        ],
    )
    parts = d.get("parts", {})
    if parts:
        labels = {
            "input_check": "input check (class ids in range)",
            "vae_encode": "VAE encode μ (first conv as a table lookup + 3 im2col matmuls + μ head)",
            "lstm_step": "LSTM step (fused gates)",
            "mdn_predict": "MDN point prediction ẑ",
            "actor": "actor 400-300",
            "decision_total": "sum of the parts, same loop",
            "encoder_total": "WorldModelEncoder.encode (all but the actor, with numpy conversions)",
        }
        ref = d.get("reference", {})
        cols = ["part", "p50", "p95", "share of decision p50"] + [
            f"module path, oneDNN {k.split('_')[1]}, p50" for k in ref
        ]
        rows = [
            [
                labels.get(k, k),
                f"{fmt(v.get('p50_ms'), 3)} ms",
                f"{fmt(v.get('p95_ms'), 3)} ms",
                f"{100 * v.get('p50_ms', 0) / p50:.0f}%" if p50 else "–",
            ]
            + [f"{fmt(r[k]['p50_ms'], 3)} ms" if k in r else "–" for r in ref.values()]
            for k, v in parts.items()
        ]
        out += [
            "Each part timed inside the same decision loop (the fast batch-1 path `FastDecision`, "
            "`worldmodel/models/fast_decision.py`), beside the same parts through the training modules in the same "
            "run:",
            "",
            table(cols, rows),
            "",
        ]
    for key, title in (
        ("profile_torch_self_cpu_top15", "torch.profiler: top 15 operators by self CPU time"),
        ("profile_python_tottime_top15", "cProfile: top 15 functions by own time"),
    ):
        if d.get(key):
            out += [
                f"<details><summary>{title} ({fmt(p.get('profile_decisions'))} decisions; profiling adds overhead)"
                "</summary>",
                "",
                "```",
                d[key].rstrip(),
                "```",
                "",
                "</details>",
                "",
            ]
    return "\n".join(out)


def section_env_views(d: dict, summary: list) -> str:
    views = d.get("views", {})
    names = list(views)
    out = ["## The camera's views side by side (`env_views.json`)", "", *provenance(d), ""]
    if not names:
        return "\n".join(out + ["No views measured.", ""])
    base = names[0]
    out += [
        "Camera-on steps/s, interleaved rounds of "
        f"{views[base].get('steps_per_round', '?')} steps, the median of {views[base].get('rounds', '?')} "
        "(conf/view/; NAME@SIZE: that view at SIZE px, the env only, since no world model takes other sizes). The "
        "ratio is of CPU time, which other work on the machine disturbs least.",
        "",
        table(
            ["view", "env keys", "steps/s (wall)", "steps/s per CPU-second", f"CPU ratio to {base}"],
            [
                [
                    n,
                    ", ".join(f"{k}={v}" for k, v in v_["env"].items()) or "–",
                    fmt(v_["steps_per_s"]),
                    fmt(v_["steps_per_s_cpu"]),
                    fmt(v_[f"cpu_ratio_to_{base}"], 2),
                ]
                for n, v_ in views.items()
            ],
        ),
        "",
    ]
    if d.get("render_cpu_ms"):
        out += [
            "TinyRenderer alone, CPU ms per frame, the same bodies drawn: a horizon band of the 90° width at 4× the "
            "pixels per degree against the 64×64 frame (`bench_env.band_render_ms`).",
            "",
            table(["render", "CPU ms"], [[k, fmt(v, 2)] for k, v in d["render_cpu_ms"].items()]),
            "",
        ]
    for n in names[1:]:
        ratio = views[n][f"cpu_ratio_to_{base}"]
        summary.append([f"env steps/s, view {n}, against {base}", f"{ratio:.2f}x", ">= 0.5x", at_least(ratio, 0.5)])
    return "\n".join(out)


def section_other(name: str, d: dict) -> str:
    scalars = {k: v for k, v in d.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    out = [f"## {name} (`{name}.json`)", "", *provenance(d), ""]
    if scalars:
        out += [table(["key", "value"], [[k, fmt(v, 3)] for k, v in scalars.items()]), ""]
    out += [f"No report section for this benchmark yet; see `benchmarks/results/{name}.json`.", ""]
    return "\n".join(out)


SECTIONS = {"env": section_env, "stages": section_stages, "decision": section_decision, "env_views": section_env_views}


def hand_written_sections(text: str) -> list[str]:
    """The sections of a RESULTS.md text marked ``BY_HAND``: each from its ``## `` heading to the next heading of
    that level, or to the end."""
    sections, current = [], None
    for line in text.splitlines():
        if line.startswith("## "):
            if current:
                sections.append(current)
            current = [line]
        elif current is not None:
            current.append(line)
    if current:
        sections.append(current)
    return ["\n".join(s).rstrip() + "\n" for s in sections if len(s) > 1 and s[1].strip() == BY_HAND]


def write_report(command: str, results_dir: Path = RESULTS_DIR, report: Path = REPORT) -> Path:
    """Rewrite ``report`` from the JSONs in ``results_dir``, keeping its sections written by hand."""
    kept = hand_written_sections(report.read_text()) if report.exists() else []
    results = {}
    for path in sorted(results_dir.glob("*.json")):
        try:
            results[path.stem] = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            print(f"[run] skipping unreadable {path}: {err}", file=sys.stderr)
    names = [n for n in ORDER if n in results] + sorted(n for n in results if n not in ORDER)

    machines = {}
    for n in names:
        m = {k: v for k, v in results[n].get("machine", {}).items() if k != "date"}
        machines.setdefault(machine_line(m), []).append(n)
    summary: list[list] = []
    sections = [SECTIONS.get(n, lambda d, s, n=n: section_other(n, d))(results[n], summary) for n in names]

    head = [
        "# Benchmark results",
        "",
        f"Generated by `{command}` from the JSON files in "
        "`benchmarks/results/`. Targets: docs/design.md §7 (2-core CPU, no GPU).",
        "",
    ]
    if not names:
        head += ["No results yet: run `python -m benchmarks.run`.", ""]
    elif len(machines) == 1:
        head += [f"**Machine:** {next(iter(machines))}.", ""]
    else:
        head += ["**Machines** (the files were not all measured on the same one):", ""]
        head += [f"* {line}: {', '.join(ns)}" for line, ns in machines.items()] + [""]
    if names:
        head += [
            "**Measured:** "
            + ", ".join(f"{n}" + (" (tiny run, not a measurement)" if is_tiny(results[n]) else "") for n in names)
            + " (each file's `machine.date` says when).",
            "",
        ]
        head += [
            "Reproduce: `python -m benchmarks.run` (all, full size; `make bench`), `--quick` for smaller sizes, "
            "`--only env|stages|decision` for one, `--report-only` to rewrite this file without measuring. "
            "On a shared or busy machine all numbers are pessimistic.",
            "",
        ]
    if summary:
        head += ["## Summary against the targets", "", table(["what", "measured", "target", "status"], summary), ""]
    report.write_text("\n".join(head + sections + kept).rstrip() + "\n")
    return report


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="smaller sizes (minutes)")
    size.add_argument(
        "--tiny", action="store_true", help="seconds-long sizes to check the scripts work (not measurements)"
    )
    size.add_argument("--report-only", action="store_true", help="only regenerate RESULTS.md from the JSONs")
    ap.add_argument("--only", action="append", choices=ORDER, help="run only this benchmark (repeatable)")
    args = ap.parse_args(argv)
    given = list(sys.argv[1:] if argv is None else argv)
    command = " ".join(["python -m benchmarks.run", *given])

    if not args.report_only:
        preset = "tiny" if args.tiny else "quick" if args.quick else "full"
        for name in [n for n in ORDER if not args.only or n in args.only]:
            run_benchmark(name, PRESETS[preset][name], preset)
    path = write_report(command)
    print(f"\n[run] wrote {path} (machine: {machine_line(machine())})")


if __name__ == "__main__":
    main()
