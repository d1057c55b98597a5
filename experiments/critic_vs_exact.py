"""Does a learned critic rank the chooser's manoeuvres as the simulator's exact costs do?

    python -m experiments.critic_vs_exact experiment=quick scale=quick [--validation-seed 4712] [--boot 2000]

The chooser's labels (``worldmodel/chooser_labels.py``) hold, on straight-line braking's states at the decision
steps t = 0 .. decide_steps - 1 of the validation bank's scenarios (``data/NAME/chooser_labels/validation-*/``,
made once if missing), the exact R2 cost (the sum of injury probabilities still to come) of starting each candidate
manoeuvre there (``agent.chooser``'s candidates: braking first, then the lane changes). This asks every trained agent
of the experiment whose checkpoint has a critic how it ranks those candidates on the same states:

* the paper's DDPG agents (``runs/NAME/agent_r1/seed*/``, ``agent_r2/...`` and their variants): the critic's
  Q(s, a_k) for each candidate's first action a_k (the simulator's action, through the agent's ``ActionMap``), s
  being the world model's view of the labelled frames as a live run feeds them (braking before each), with the
  agent's own encoder settings. Q is a return (R1: people involved, R2: injury probabilities, both negative), so
  -Q is its cost; it values taking a_k once and then following the actor, not holding the manoeuvre;
* the counterfactual-cost actors (``agent_r2_counterfactual/seed*/``), whose ``CostCritic`` predicts the R2 cost of
  a shift (``envs/counterfactual.py``): a lane change at full braking is the shift with that steer, ``u1 = 0`` and
  ``u2`` giving its hold, braking is ``u = 0``. Its labels allow a second decision later, and its critic only
  predicts at its own decisions, so it is compared at t = 0 only (its decision d = 0).

Agents that see the true state (``obs=privileged``) or anything other than the world model, the chooser (whose
scorer *is* a cost model of these very candidates; ``experiments.chooser_floor`` scores it), DQNs and the peers'
agents are left out, and the output says which and why. The test bank is never touched: a sealed seed or
``evaluate.bank=test`` is refused.

Columns (per agent, decision steps ``t``, and states: those where some candidate is cheaper than braking by more
than 0.01, where the decision matters, and all):

* ``states`` / ``scenarios``: labelled decision states and the scenarios they come from;
* ``Spearman``: per state, the rank correlation between the critic's cost (-Q) and the exact costs across the
  candidates (states where every candidate costs the same are left out; a critic constant on a state counts 0),
  averaged over states, with a bootstrap 95 % interval over scenarios;
* ``pairwise``: over every state's candidate pairs whose exact costs differ, the share the critic orders the same
  way (a tie in Q counts half: any constant critic gives 0.5), with the same interval;
* ``argmax Q lowest``: the share of states where the candidate of highest Q is one of lowest exact cost; beside
  it ``braking lowest``, the share where braking (candidate 0) is: what always braking gets;
* ``argmax Q brakes``: the share of states where the critic prefers braking;
* ``pick - braking``: the mean exact cost of the critic's choice minus braking's, in points of R2 (100 x):
  negative where acting on the critic's ranking at that state would beat braking.

Each table starts with what a uniformly random choice among the candidates gets (in expectation: Spearman 0,
pairwise 0.5), the chance level the critics are to be read against.

Writes ``runs/NAME/critic_vs_exact/critic_vs_exact.md`` (the tables printed here) and ``critic_vs_exact.csv`` (per
agent and state: its scores and exact costs per candidate, Spearman, pairs ordered).
"""

from __future__ import annotations

import argparse
import csv
import logging
from dataclasses import dataclass

import numpy as np
import torch

from envs.chooser import decide_steps_for
from worldmodel import artifacts, chooser, loading
from worldmodel.action_map import ActionMap
from worldmodel.banks import dir_suffix, sealed_seed_problem, validation_draw
from worldmodel.config import compose

log = logging.getLogger("critic_vs_exact")
TIE = 1e-6  # exact costs closer than this are equal
MATTERS = 0.01  # R2 units: a state where some candidate beats braking by more than this is one where choosing matters
BOOT_SEED = 20_240


# ----------------------------------------------------------------------------- the comparison
def per_state(scores: np.ndarray, costs: np.ndarray) -> dict[str, np.ndarray]:
    """Per state (rows), how the critic's ``scores`` (a cost: lower is better) rank the candidates (columns) against
    their exact ``costs``: ``spearman`` (NaN where every exact cost is equal; 0 where the scores are constant),
    ``pairs`` (candidate pairs whose exact costs differ) and ``agree`` (of those, the ones ordered alike, a tie in
    the scores counting half), ``pick`` (the candidate of lowest score, the first of equal ones), whether it and
    braking are of lowest exact cost (``pick_lowest``, ``brake_lowest``), and ``pick_minus_brake`` (exact)."""
    from worldmodel.stats import rank_agreement

    scores, costs = np.asarray(scores, np.float64), np.asarray(costs, np.float64)
    n = len(costs)
    agreement = rank_agreement(scores, costs, TIE)
    pick = np.argmin(scores, axis=1)
    lowest = costs.min(axis=1) + TIE
    picked = costs[np.arange(n), pick]
    return {
        **agreement,
        "pick": pick,
        "pick_lowest": picked <= lowest,
        "brake_lowest": costs[:, 0] <= lowest,
        "pick_minus_brake": picked - costs[:, 0],
    }


def matters(costs: np.ndarray, by: float = MATTERS) -> np.ndarray:
    """States where some candidate is cheaper than braking (candidate 0) by more than ``by`` (the cost's unit)."""
    return (costs[:, :1] - costs[:, 1:]).max(axis=1) > by


def _ratio_ci(num: np.ndarray, den: np.ndarray, episode: np.ndarray, boot: int, seed: int) -> tuple[float, float]:
    """A bootstrap 95 % interval of sum(num) / sum(den) over rows, resampling whole scenarios (``episode``)."""
    if boot <= 0 or len(num) == 0:
        return float("nan"), float("nan")
    keys, inv = np.unique(episode, return_inverse=True)
    n_e = np.bincount(inv, weights=num, minlength=len(keys))
    d_e = np.bincount(inv, weights=den, minlength=len(keys))
    rng = np.random.default_rng(seed)
    w = rng.multinomial(len(keys), np.full(len(keys), 1.0 / len(keys)), size=boot).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        stats = (w @ n_e) / (w @ d_e)
    stats = stats[np.isfinite(stats)]
    if len(stats) == 0:
        return float("nan"), float("nan")
    lo, hi = np.percentile(stats, [2.5, 97.5])
    return float(lo), float(hi)


def summarize(scores: np.ndarray, costs: np.ndarray, episode: np.ndarray, boot: int = 2000, seed: int = BOOT_SEED):
    """The figures of one table row over the given states (see the module's docstring), with ``per_state``'s arrays
    under ``rows``."""
    s = per_state(scores, costs)
    ok = np.isfinite(s["spearman"])
    rho = np.where(ok, s["spearman"], 0.0)
    n = len(costs)
    return {
        "states": n,
        "scenarios": len(np.unique(episode)),
        "ranked_states": int(ok.sum()),
        "spearman": float(rho.sum() / ok.sum()) if ok.any() else float("nan"),
        "spearman_ci": _ratio_ci(rho, ok.astype(np.float64), episode, boot, seed),
        "pairwise": float(s["agree"].sum() / s["pairs"].sum()) if s["pairs"].sum() else float("nan"),
        "pairwise_ci": _ratio_ci(s["agree"], s["pairs"].astype(np.float64), episode, boot, seed),
        "pick_lowest": float(s["pick_lowest"].mean()) if n else float("nan"),
        "brake_lowest": float(s["brake_lowest"].mean()) if n else float("nan"),
        "pick_brakes": float((s["pick"] == 0).mean()) if n else float("nan"),
        "pick_minus_brake": float(s["pick_minus_brake"].mean()) if n else float("nan"),
        "rows": s,
    }


# ----------------------------------------------------------------------------- the critics
def _linear_outs(sd: dict, prefix: str) -> list[int]:
    """The output sizes of the linear layers of the ``nn.Sequential`` whose state-dict keys start with ``prefix``."""
    found = []
    for k, v in sd.items():
        rest = k[len(prefix) :]
        if k.startswith(prefix) and rest.endswith(".weight") and rest.split(".")[0].isdigit() and v.dim() == 2:
            found.append((int(rest.split(".")[0]), int(v.shape[0])))
    return [out for _, out in sorted(found)]


def ddpg_critic(state: dict):
    """The DDPG checkpoint's critic (the first of twin critics, the one its actor ascends), in eval mode; its sizes
    are read from the weights."""
    from worldmodel.models.ddpg import Critic

    sd = state["agent"]["critic"]
    layer = 1 if any(k.startswith("first.") for k in sd) else 0
    outs = _linear_outs(sd, "first.") + _linear_outs(sd, "net.")
    critic = Critic(int(state["obs_dim"]), 2, outs[:-1], layer)
    critic.load_state_dict(sd)
    return critic.eval()


def ddpg_scores(state: dict, encoded: np.ndarray, speed: np.ndarray, candidates) -> np.ndarray:
    """-Q(s, a_k) for every state (rows) and candidate's first action a_k (columns): the critic's cost."""
    critic = ddpg_critic(state)
    amap = ActionMap.from_dict(state.get("action_map"))
    first = [m.action(0) for m in candidates]
    u = np.stack([[amap.from_env(a, float(v)) for a in first] for v in speed]).astype(np.float32)
    s, k = u.shape[:2]
    with torch.inference_mode():
        q = critic(torch.from_numpy(np.repeat(encoded, k, axis=0)), torch.from_numpy(u.reshape(-1, 2)))
    return -q.reshape(s, k).numpy().astype(np.float64)


def shift_inputs(candidates, hold_s, step_s: float) -> np.ndarray:
    """The counterfactual critic's ``u`` (``envs.counterfactual.ShiftSpace``) of every candidate, (K, 3): braking
    is ``u = 0``; a lane change is the shift of its steer, pedal and hold. Raises ValueError for a candidate no
    shift drives exactly as the chooser does (a held swerve, a delayed start, a hold outside ``hold_s``)."""
    from envs.counterfactual import ShiftSpace

    space = ShiftSpace(tuple(float(h) for h in hold_s), float(step_s))
    lo, hi = (float(h) for h in hold_s)
    out = []
    for m in candidates:
        pedal_u = (float(m.pedal) + 1.0) / 2.0
        if not m.steer:
            u = [0.0, pedal_u, 0.0]
        elif m.shape == "lane_change" and m.delay == 0 and hi > lo:
            u = [float(m.steer), pedal_u, 2.0 * (m.hold * float(step_s) - lo) / (hi - lo) - 1.0]
        else:
            raise ValueError(f"no shift drives {m}")
        shift = space.shift(u)
        horizon = 2 * max(int(m.hold), shift.hold) + 3
        if abs(u[2]) > 1.0 + 1e-9 or any(not np.allclose(shift.action(k), m.action(k)) for k in range(horizon)):
            raise ValueError(f"no shift drives {m} (hold_s {list(hold_s)}, step {step_s} s)")
        out.append(u)
    return np.asarray(out, np.float32)


def cost_critic(state: dict):
    """The counterfactual checkpoint's ``CostCritic`` (eval mode), its sizes read from the weights."""
    from worldmodel.models.counterfactual import CostCritic

    sd = state["critic"]  # each member a first layer of its own, u joining after it
    members = len({k.split(".")[1] for k in sd if k.startswith("trunks.")})
    hidden = _linear_outs(sd, "trunks.0.") + _linear_outs(sd, "heads.0.")[:-1]
    critic = CostCritic(int(state["in_dim"]), members, hidden, aux_dim=int(sd["aux.0.weight"].shape[0]))
    critic.load_state_dict(sd)
    return critic.eval()


def counterfactual_scores(state: dict, encoded: np.ndarray, candidates) -> np.ndarray:
    """The counterfactual critic's predicted cost (members' mean) of every candidate on states at its decision 0."""
    from worldmodel.models import counterfactual as counterfactual_models

    u = shift_inputs(candidates, state["hold_s"], float(state["step_s"]))
    x = counterfactual_models.features(encoded, np.zeros(len(encoded)), int(state["decisions"]))
    if x.shape[1] != int(state["in_dim"]):
        raise ValueError(f"its critic reads {state['in_dim']} features, the world model gives {x.shape[1]}")
    critic = cost_critic(state)
    with torch.inference_mode():
        xt = torch.from_numpy(np.repeat(x, len(u), axis=0))
        ut = torch.from_numpy(np.tile(u, (len(x), 1)))
        return critic(xt, ut).mean(0).reshape(len(x), len(u)).numpy().astype(np.float64)


# ----------------------------------------------------------------------------- the agents
@dataclass
class Scored:
    key: str
    kind: str  # "DDPG Q" or "cost critic"
    scores: np.ndarray  # (rows, K): the critic's cost
    rows: np.ndarray  # the labelled states (indices) it was scored on


def score_agents(cfg, val: dict, candidates) -> tuple[list[Scored], list[str]]:
    """Every trained agent of the experiment's paper family with a critic, scored on the labelled states; and a line
    for each agent left out, saying why."""
    encoded: dict[tuple, np.ndarray] = {}

    def view(settings: dict) -> tuple[np.ndarray, int]:
        key = tuple(sorted(settings.items()))
        if key not in encoded:
            encoder = loading.load_world_model(cfg, **settings)
            encoded[key] = chooser.encode_labels(encoder, val)
        return encoded[key], encoded[key].shape[1]

    scored, skipped = [], []
    for agent in artifacts.trained_agents(cfg, "porav"):
        state = loading.load_agent_state(cfg, agent, "last")
        learner, obs = state.get("learner", "ddpg"), state.get("obs", "worldmodel")
        if learner == "chooser":
            skipped.append(f"{agent.key}: the chooser, whose scorer is a cost model of these candidates (no critic)")
            continue
        if obs != "worldmodel":
            skipped.append(f"{agent.key}: it sees obs={obs}, not the world model's view of the frames")
            continue
        if learner == "ddpg" and "critic" in state.get("agent", {}):
            x, dim = view(loading.agent_input(state, cfg.vae.latent_dim))
            if dim != int(state["obs_dim"]):
                skipped.append(f"{agent.key}: it reads {state['obs_dim']} inputs, the world model gives {dim}")
                continue
            rows = np.arange(len(x))
            scored.append(Scored(agent.key, "DDPG -Q", ddpg_scores(state, x, val["speed"], candidates), rows))
        elif learner == "counterfactual" and state.get("critic_obs") == "privileged":
            skipped.append(f"{agent.key}: its critic reads the true state (critic_obs=privileged), not these frames")
        elif learner == "counterfactual" and state.get("critic") is not None:
            x, _ = view(loading.agent_input(state, cfg.vae.latent_dim))
            rows = np.flatnonzero(val["t"] == 0)
            try:
                scores = counterfactual_scores(state, x[rows], candidates)
            except (ValueError, RuntimeError, KeyError) as err:
                skipped.append(f"{agent.key}: {err}")
                continue
            scored.append(Scored(agent.key, "cost critic (t = 0)", scores, rows))
        else:
            skipped.append(f"{agent.key}: learner {learner} without a critic over these actions")
    return scored, skipped


# ----------------------------------------------------------------------------- the report
def _fmt(x: float, ci: tuple[float, float] | None = None, digits: int = 2) -> str:
    if not np.isfinite(x):
        return "n/a"
    text = f"{x:.{digits}f}"
    if ci is not None and np.isfinite(ci[0]):
        text += f" ({ci[0]:.{digits}f} to {ci[1]:.{digits}f})"
    return text


def header(unit: str = "pts") -> list[str]:
    return [
        "| agent | critic | t | states | scenarios | Spearman (95 % CI) | pairwise (95 % CI) | argmax Q lowest % | "
        f"braking lowest % | argmax Q brakes % | pick - braking, {unit} |",
        "|---|---|---|---:|---:|---|---|---:|---:|---:|---:|",
    ]


def table(
    scored: list[Scored],
    val: dict,
    steps: int,
    subset: str,
    boot: int,
    matters_by: float = MATTERS,
    points: float = 100.0,
    unit: str = "pts",
) -> list[str]:
    """One markdown table: every agent's rows on ``subset`` ("matters" or "all") of its states, t = 0 .. steps-1
    pooled and t = 0 alone. ``matters_by``: ``matters``'s margin; ``points`` and ``unit``: the last column's scale
    and name (100, "pts": R2's probabilities as points)."""
    costs, episode, t = val["costs"].astype(np.float64), val["episode"], val["t"]
    lines = header(unit)
    windows = [(f"0-{steps - 1}", np.ones(len(t), bool))] if steps > 1 else []
    for label, in_window in [*windows, ("0", t == 0)]:  # what a uniformly random choice of candidate gets
        keep = in_window & (matters(costs, matters_by) if subset == "matters" else True)
        y, lowest = costs[keep], costs[keep].min(axis=1, keepdims=True) + TIE
        nan = not len(y)
        share, brake = (np.nan, np.nan) if nan else ((y <= lowest).mean(), (y[:, 0] <= lowest[:, 0]).mean())
        gain = np.nan if nan else (y.mean(axis=1) - y[:, 0]).mean()
        lines.append(
            f"| uniform random candidate | (expected) | {label} | {len(y)} | {len(np.unique(episode[keep]))} | "
            f"0 | 0.5 | {_fmt(100 * share, digits=1)} | {_fmt(100 * brake, digits=1)} | "
            f"{_fmt(100 / costs.shape[1], digits=1)} | {_fmt(points * gain)} |"
        )
    for s in scored:
        windows = [("0", t[s.rows] == 0)]
        if steps > 1 and not (t[s.rows] == 0).all():
            windows.insert(0, (f"0-{steps - 1}", np.ones(len(s.rows), bool)))
        for label, in_window in windows:
            keep = in_window & (matters(costs[s.rows], matters_by) if subset == "matters" else True)
            r = s.rows[keep]
            f = summarize(s.scores[keep], costs[r], episode[r], boot)
            lines.append(
                f"| {s.key} | {s.kind} | {label} | {f['states']} | {f['scenarios']} | "
                f"{_fmt(f['spearman'], f['spearman_ci'])} | {_fmt(f['pairwise'], f['pairwise_ci'])} | "
                f"{_fmt(100 * f['pick_lowest'], digits=1)} | {_fmt(100 * f['brake_lowest'], digits=1)} | "
                f"{_fmt(100 * f['pick_brakes'], digits=1)} | {_fmt(points * f['pick_minus_brake'])} |"
            )
    return lines


def write_csv(path, scored: list[Scored], val: dict, matters_by: float = MATTERS) -> None:
    costs = val["costs"].astype(np.float64)
    k = costs.shape[1]
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(
            [
                "agent",
                "episode",
                "t",
                "matters",
                "spearman",
                "pairs",
                "agree",
                "pick",
                "pick_lowest",
                "brake_lowest",
                *(f"score_{j}" for j in range(k)),
                *(f"cost_{j}" for j in range(k)),
            ]
        )
        for s in scored:
            y = costs[s.rows]
            rows, m = per_state(s.scores, y), matters(y, matters_by)
            for i, r in enumerate(s.rows):
                w.writerow(
                    [
                        s.key,
                        int(val["episode"][r]),
                        int(val["t"][r]),
                        int(m[i]),
                        "" if not np.isfinite(rows["spearman"][i]) else f"{rows['spearman'][i]:.4f}",
                        int(rows["pairs"][i]),
                        f"{rows['agree'][i]:g}",
                        int(rows["pick"][i]),
                        int(rows["pick_lowest"][i]),
                        int(rows["brake_lowest"][i]),
                        *(f"{v:.6g}" for v in s.scores[i]),
                        *(f"{v:.6g}" for v in y[i]),
                    ]
                )


def write_report(
    cfg,
    stem: str,
    head: list[str],
    scored: list[Scored],
    skipped: list[str],
    val: dict,
    steps: int,
    boot: int,
    matters_by: float = MATTERS,
    points: float = 100.0,
    unit: str = "pts",
    margin_unit: str = "",
) -> str:
    """``head``, the agents left out, the tables on the states that matter and on all states, written as
    ``runs/NAME/critic_vs_exact/<stem>.md`` with the per-state ``<stem>.csv``; returns the text."""
    units = {"matters_by": matters_by, "points": points, "unit": unit}
    lines = [
        *head,
        *(["Left out: " + "; ".join(skipped) + ".", ""] if skipped else []),
        f"States where the decision matters (some candidate cheaper than braking by > {matters_by:g}{margin_unit}):",
        "",
        *table(scored, val, steps, "matters", boot, **units),
        "",
        "All states:",
        "",
        *table(scored, val, steps, "all", boot, **units),
    ]
    if not scored:
        lines += ["", "No trained agent with a critic over these actions was found."]
    out = artifacts.runs_root(cfg) / "critic_vs_exact"
    out.mkdir(parents=True, exist_ok=True)
    text = "\n".join(lines) + "\n"
    (out / f"{stem}.md").write_text(text)
    write_csv(out / f"{stem}.csv", scored, val, matters_by)
    return text


def first_action_note(candidates) -> str:
    """Whether the candidates' first actions are distinct (a critic of one action cannot tell apart two that start
    alike, e.g. a held swerve and a lane change of the same steer)."""
    groups: dict[tuple, list[int]] = {}
    for j, m in enumerate(candidates):
        groups.setdefault(tuple(np.round(m.action(0), 6).tolist()), []).append(j)
    shared = [g for g in groups.values() if len(g) > 1]
    if not shared:
        return "Their first actions are distinct, so a DDPG critic can tell every candidate apart."
    return (
        "Candidates " + "; ".join(", ".join(map(str, g)) for g in shared) + " start with the same action and so share "
        "the DDPG critic's Q (it cannot order them: they count as ties)."
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick scale=quick")
    parser.add_argument(
        "--validation-seed", type=validation_draw, default=None, help="the validation draw (default: the config's)"
    )
    parser.add_argument("--boot", type=int, default=2000, help="bootstrap resamples of the scenarios")
    args = parser.parse_intermixed_args(argv)  # Hydra overrides may come after the options
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    base = [*args.overrides, "reward=r2", "agent=chooser"]
    if args.validation_seed is not None:
        base.append(f"evaluate.validation_seed={args.validation_seed}")
    cfg = compose("train_agent", base)
    if cfg.evaluate.bank != "validation":
        parser.error("evaluate.bank=test: the test bank is sealed, and this script compares on the validation bank")
    why = sealed_seed_problem(cfg.evaluate.validation_seed)
    if why:
        parser.error(why.split(";")[0] + ": choose a validation draw (worldmodel/banks.py)")
    c = chooser.cfg_chooser(cfg)
    candidates = c.candidates(cfg.env.step_s)
    steps = decide_steps_for(c.decide_s, cfg.env.step_s)
    val = chooser.labels(cfg, "validation")
    scored, skipped = score_agents(cfg, val, candidates)
    costs = val["costs"]
    n_matter = int(matters(costs).sum())
    names = ", ".join(
        f"{j}: braking"
        if not m.steer
        else f"{j}: {m.shape.replace('_', ' ')} steer {m.steer:+g}, pedal {m.pedal:g}, hold {m.hold} steps"
        for j, m in enumerate(candidates)
    )
    lines = [
        f"Experiment {cfg.experiment}, validation bank seed {cfg.evaluate.validation_seed}: "
        f"{len(np.unique(val['episode']))} scenarios, {len(costs)} labelled decision states (t = 0-{steps - 1}), "
        f"{n_matter} of them where some candidate beats braking by more than {MATTERS:g} (R2).",
        "",
        f"Candidates ({names}). {first_action_note(candidates)}",
        "",
        "Scores: DDPG -Q(s, a_k) for each candidate's first action; the counterfactual critic's predicted cost of the "
        "equivalent shift. Intervals: bootstrap 95 % over scenarios.",
        "",
    ]
    suffix = dir_suffix("validation", "porav", cfg.evaluate.validation_seed)
    text = write_report(cfg, f"critic_vs_exact{suffix}", lines, scored, skipped, val, steps, args.boot)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
