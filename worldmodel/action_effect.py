"""The action effect: does the world model's dream move the way the simulator does under each action?

The simulator's snapshots are the ground truth. In held-out scenarios (their own seed stream, never collected), the
autopilot drives ``warmup`` steps; the env is snapshotted and rolled ``horizon`` real steps under each of
:data:`ACTIONS` from the same state (``branch_bank``). The *real* effect of an action at +k is the share of pixels
where its branch differs from the "keep going" branch (overall, and per class: pixels where exactly one of the two
frames shows the class); the *dreamt* effect is the same between the decoded dreams of the LSTM
(``worldmodel/dreams.py`` dreams them). This module turns the two sets of frames into per-point rows
(``effect_rows``, written as gzip CSV) and their summary with bootstrap intervals (``summarise_effect``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from envs import CLASS_NAMES
from envs.streams import DREAM_BRANCH_SCENARIOS

# [steer, throttle/brake]: steer -1 is full left, pedal -1 full braking. "keep" is the reference branch.
# Half steering tells whether the LSTM scales its dream with the input where grip caps the yaw rate (at 10-20 m/s
# the real car turns alike at 0.5 and 1.0).
ACTIONS: dict[str, tuple[float, float]] = {
    "keep": (0.0, 0.0),
    "brake": (0.0, -1.0),
    "left": (-1.0, 0.0),
    "right": (1.0, 0.0),
    "left_half": (-0.5, 0.0),
    "right_half": (0.5, 0.0),
    "brake_left": (-1.0, -1.0),
    "brake_right": (1.0, -1.0),
}
EFFECT_CLASSES = {"vehicles": "Vehicles", "pedestrians": "Pedestrians", "roads": "Roads"}


# ----------------------------------------------------------------------------- real branches
def branch_bank(
    env,
    points: int,
    horizon: int = 10,
    warmup: int = 8,
    seed: int = 0,
    speeds: tuple[float, ...] = (10.0, 20.0),
    autopilot: dict | None = None,
) -> dict:
    """Real branches from ``points`` held-out branch points; ``env`` must have a camera.

    Scenario k is drawn from the paper's distribution with the seed stream ``[seed, DREAM_BRANCH_SCENARIOS, k]``
    (``envs/streams.py``; disjoint from the collection's ``[seed, index]``), at speed ``speeds[k % len(speeds)]``; an
    episode that ends during the warm-up is replaced by the next draw. Returns ``context_seg (N, warmup + 1, H, W)``
    (the last is the branch point), ``context_action (N, warmup, 2)``, ``seg (N, A, horizon, H, W)`` with ``[:, a,
    k]`` the frame k + 1 steps after the branch point under action ``a`` (in :data:`ACTIONS` order), ``valid (N, A,
    horizon)`` (false after that branch's episode ended) and ``speed (N,)``.
    """
    from envs import NoisyAutopilot, sample_scenario

    ap = dict(autopilot or {})
    if "excursion_s" in ap:
        ap["excursion_s"] = tuple(ap["excursion_s"])
    actions = np.asarray(list(ACTIONS.values()), np.float32)
    out = {k: [] for k in ("context_seg", "context_action", "seg", "valid", "speed")}
    k = 0
    while len(out["speed"]) < points:
        rng = np.random.default_rng([int(seed), DREAM_BRANCH_SCENARIOS, k])
        spec = dataclasses.replace(sample_scenario(rng), ego_speed=float(speeds[k % len(speeds)]))
        k += 1
        frames, acts, ended = _drive(env, NoisyAutopilot(**ap), spec, warmup)
        if len(acts) < warmup or any(ended):
            continue
        snap = env.snapshot()
        seg = np.zeros((len(actions), horizon, *frames[0].shape), np.uint8)
        valid = np.zeros((len(actions), horizon), bool)
        for a, action in enumerate(actions):
            env.restore(snap)
            last = frames[-1]
            for h in range(horizon):
                if h == 0 or valid[a, h - 1]:
                    obs, _, terminated, truncated, _ = env.step(action)
                    last, valid[a, h] = obs["seg"], True
                    if terminated or truncated:
                        seg[a, h] = last
                        seg[a, h + 1 :] = last
                        break
                seg[a, h] = last
        out["context_seg"].append(np.stack(frames))
        out["context_action"].append(np.asarray(acts, np.float32))
        out["seg"].append(seg)
        out["valid"].append(valid)
        out["speed"].append(spec.ego_speed)
    return {key: np.stack(v) for key, v in out.items()}


def _drive(env, policy, spec, steps: int) -> tuple[list, list, list]:
    """The first ``steps`` steps of ``spec`` under ``policy``: frames (one more than actions), actions, and
    whether the episode had ended after each step."""
    from envs import rollout

    frames, acts, ended = [], [], []

    def on_step(obs, a, reward, info):
        frames.append(obs["seg"])
        acts.append(a)
        ended.append("outcome" in info)

    rollout(env, policy, spec, max_steps=steps, on_reset=lambda obs, info: frames.append(obs["seg"]), on_step=on_step)
    return frames, acts, ended


def branch_differences(seg: np.ndarray) -> dict[str, np.ndarray]:
    """Per branch against branch 0 ("keep"): ``seg (N, A, K, H, W)`` -> share of differing pixels ``(N, A, K)``,
    overall (``"all"``) and per class in :data:`EFFECT_CLASSES` (pixels where exactly one of the two shows it)."""
    ref = seg[:, :1]
    out = {"all": (seg != ref).mean(axis=(-1, -2))}
    for key, name in EFFECT_CLASSES.items():
        c = CLASS_NAMES.index(name)
        out[key] = ((seg == c) != (ref == c)).mean(axis=(-1, -2))
    return out


EFFECT_KEYS = ("all", *EFFECT_CLASSES)
# the per-point counts a summary is made of (effect_rows): each a plain number, so the rows can be committed
DIRECTION_KEYS = ("dream", "blind", "vae")


def effect_rows(
    real_seg: np.ndarray, dreamt_seg: np.ndarray, valid: np.ndarray, recon_seg: np.ndarray | None = None, speed=None
) -> list[dict]:
    """One row per branch point, action (but "keep") and horizon where the branch and "keep" are both running:

    * ``real_<key>`` / ``dreamt_<key>``: the share of pixels that differ from "keep" (``key`` in :data:`EFFECT_KEYS`:
      all pixels, or those where exactly one of the two frames shows the class);
    * ``match`` / ``blind_match``: pixel accuracy of the dream under the action, and of the dream under "keep"
      (what an action-blind model shows), against the real frame under the action;
    * ``changed``: pixels the action really changed (real branch against real "keep"), and on those, how many the
      dream under the action (``hits_dream``), the dream under "keep" (``hits_blind``) and the VAE's own
      reconstruction of the real frame (``hits_vae``; absent without ``recon_seg``) show in their true class.
    """
    real, dreamt = branch_differences(real_seg), branch_differences(dreamt_seg)
    both = valid & valid[:, :1]
    changed = real_seg != real_seg[:, :1]
    true = real_seg
    hits = {"dream": (dreamt_seg == true) & changed, "blind": (dreamt_seg[:, :1] == true) & changed}
    if recon_seg is not None:
        hits["vae"] = (recon_seg == true) & changed
    match = (dreamt_seg == true).mean((-1, -2))
    blind_match = (dreamt_seg[:, :1] == true).mean((-1, -2))
    rows = []
    names = list(ACTIONS)
    for i, a, k in zip(*np.nonzero(both), strict=True):
        if a == 0:
            continue
        row = {"point": int(i), "action": names[a], "horizon": int(k) + 1}
        if speed is not None:
            row["speed"] = float(speed[i])
        for key in EFFECT_KEYS:
            row[f"real_{key}"] = float(real[key][i, a, k])
            row[f"dreamt_{key}"] = float(dreamt[key][i, a, k])
        row["match"], row["blind_match"] = float(match[i, a, k]), float(blind_match[i, a, k])
        row["changed"] = int(changed[i, a, k].sum())
        for name, h in hits.items():
            row[f"hits_{name}"] = int(h[i, a, k].sum())
        rows.append(row)
    return rows


def _ratio_of_sums(top, bottom, axis=-1):
    """sum(top) / sum(bottom), nan where the bottom sums to 0 (a bootstrap statistic)."""
    t, b = np.sum(top, axis=axis), np.sum(bottom, axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(b > 0, t / np.where(b > 0, b, 1), np.nan)


def _interval(top, bottom, boot: int) -> list[float | None]:
    from .stats import paired_bootstrap_ci

    if not boot or len(top) < 2:
        return [None, None]
    low, high = paired_bootstrap_ci([top, bottom], _ratio_of_sums, boot, seed=0)
    return [None if not np.isfinite(x) else float(x) for x in (low, high)]


def write_effect_rows(rows: list[dict], path) -> None:
    """The rows as gzip CSV with no timestamp (the same rows give the same bytes)."""
    import csv
    import gzip
    import io

    from .common import atomic_write_bytes

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, gzip.compress(buf.getvalue().encode(), compresslevel=9, mtime=0))


def read_effect_rows(path) -> list[dict]:
    import csv
    import gzip

    with gzip.open(path, "rt", newline="") as fh:
        return [
            {k: v if k == "action" else (float(v) if "." in v or "e" in v else int(v)) for k, v in r.items()}
            for r in csv.DictReader(fh)
        ]


def summarise_effect(rows: list[dict], horizons: int, points: int, boot: int = 2000) -> dict:
    """The action effect from :func:`effect_rows`, per action and horizon: real and dreamt effects per class and
    their ratio (dreamt over real, of the means over the points), the ratio's 95 % interval (paired bootstrap over
    branch points, worldmodel/stats.py), pixel accuracy of the dream and of the blind dream, and the direction
    score: on the pixels the action really changed, the share the dream shows in their true class, beside the
    blind dream and the VAE's reconstruction, each with its interval. ``boot=0``: no intervals."""
    result: dict = {"points": int(points), "horizons": list(range(1, horizons + 1)), "actions": {}}
    for name in list(ACTIONS)[1:]:
        mine = [r for r in rows if r["action"] == name]
        entry: dict = {"real": {}, "dreamt": {}, "ratio": {}, "ratio_ci95": [], "direction": {}, "points": []}
        at = [[r for r in mine if r["horizon"] == k] for k in result["horizons"]]
        for key in EFFECT_KEYS:
            real = [float(np.mean([r[f"real_{key}"] for r in h])) if h else 0.0 for h in at]
            dreamt = [float(np.mean([r[f"dreamt_{key}"] for r in h])) if h else 0.0 for h in at]
            entry["real"][key], entry["dreamt"][key] = real, dreamt
            entry["ratio"][key] = [d / r if r > 0 else None for d, r in zip(dreamt, real, strict=True)]
        entry["ratio_ci95"] = [_interval([r["dreamt_all"] for r in h], [r["real_all"] for r in h], boot) for h in at]
        entry["match"] = [float(np.mean([r["match"] for r in h])) if h else 0.0 for h in at]
        entry["blind_match"] = [float(np.mean([r["blind_match"] for r in h])) if h else 0.0 for h in at]
        for key in DIRECTION_KEYS:
            if not mine or f"hits_{key}" not in mine[0]:
                continue
            score = [_ratio_of_sums([r[f"hits_{key}"] for r in h], [r["changed"] for r in h]) for h in at]
            entry["direction"][key] = {
                "score": [None if not np.isfinite(x) else float(x) for x in score],
                "ci95": [_interval([r[f"hits_{key}"] for r in h], [r["changed"] for r in h], boot) for h in at],
            }
        entry["points"] = [len(h) for h in at]
        result["actions"][name] = entry
    return result


def action_effect(
    real_seg: np.ndarray, dreamt_seg: np.ndarray, valid: np.ndarray, recon_seg: np.ndarray | None = None, boot=0
) -> dict:
    """:func:`summarise_effect` of :func:`effect_rows`: the metric straight from the branch frames."""
    rows = effect_rows(real_seg, dreamt_seg, valid, recon_seg)
    return summarise_effect(rows, real_seg.shape[2], len(real_seg), boot)


def effect_at(result: dict, horizon: int = 5, key: str = "all") -> dict[str, float | None]:
    """The ratio dreamt/real at ``horizon`` for every action: the headline numbers."""
    i = result["horizons"].index(horizon) if horizon in result["horizons"] else -1
    return {name: e["ratio"][key][i] for name, e in result["actions"].items()}


# ----------------------------------------------------------------------------- reports
def _with_interval(value, interval, digits: int) -> str:
    if value is None:
        return "–"
    low, high = interval or (None, None)
    return f"{value:.{digits}f}" + ("" if low is None else f" [{low:.{digits}f}, {high:.{digits}f}]")


def effect_headline_markdown(effect: dict, horizons=(5, 10)) -> list[str]:
    """Per action: dreamt / real with its interval, and the direction score of the dream beside the blind dream's
    and the VAE's, at a few horizons."""
    ks = [k for k in horizons if k in effect["horizons"]]
    lines = [
        f"Action effect over {effect['points']} held-out branch points, 95 % intervals from a paired bootstrap "
        "over the points. *Size*: pixels that differ from the 'keep' branch, dreamt over real (1 = the dream "
        "moves as much as the simulator). *Direction*: on the pixels the action really changed, the share shown "
        "in their true class by the dream under the action, by the dream under 'keep' (action-blind) and by the "
        "VAE's reconstruction of the real frame (the best a dream could show).",
        "",
        "| action | horizon | points | size: dreamt / real | direction: dream | action-blind dream | VAE |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, entry in effect["actions"].items():
        for k in ks:
            i = effect["horizons"].index(k)
            cells = [
                name,
                f"+{k}",
                str(entry["points"][i]),
                _with_interval(
                    entry["ratio"]["all"][i], entry.get("ratio_ci95", [None] * len(effect["horizons"]))[i], 2
                ),
            ]
            for key in DIRECTION_KEYS:
                d = entry.get("direction", {}).get(key)
                cells.append("–" if d is None else _with_interval(d["score"][i], d["ci95"][i], 3))
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def effect_markdown(effect: dict, horizons=(1, 3, 5, 10)) -> list[str]:
    """The action effect's tables: the headline per action, real, dreamt and their ratio per class, and how
    much the dream under an action looks like the real branch (lines of markdown)."""
    lines = []
    ks = [k for k in horizons if k in effect["horizons"]]
    lines += [*effect_headline_markdown(effect), ""]
    lines += [
        f"Action effect over {effect['points']} held-out branch points: share of pixels that differ from the "
        "'keep' branch, real (simulator) and dreamt (LSTM), and their ratio.",
        "",
        "| action | class | " + " | ".join(f"real +{k} | dreamt +{k} | ratio +{k}" for k in ks) + " |",
        "|---|---|" + "---:|---:|---:|" * len(ks),
    ]
    for name, entry in effect["actions"].items():
        for key in entry["real"]:
            cells = []
            for k in ks:
                i = effect["horizons"].index(k)
                ratio = entry["ratio"][key][i]
                cells.append(
                    f"{entry['real'][key][i]:.3f} | {entry['dreamt'][key][i]:.3f} | "
                    + ("–" if ratio is None else f"{ratio:.2f}")
                )
            lines.append(f"| {name} | {key} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Does the dream under an action look like the real future under it? Pixel accuracy of the decoded dream "
        "against the real branch frame, beside the dream under 'keep' against the same real frame (an "
        "action-blind model's score):",
        "",
        "| action | " + " | ".join(f"dream +{k} | blind +{k}" for k in ks) + " |",
        "|---|" + "---:|---:|" * len(ks),
    ]
    for name, entry in effect["actions"].items():
        if "match" in entry:
            cells = [
                f"{entry['match'][effect['horizons'].index(k)]:.3f} | "
                f"{entry['blind_match'][effect['horizons'].index(k)]:.3f}"
                for k in ks
            ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    return lines
