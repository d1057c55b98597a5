"""Kim's LIDAR student against its teacher: where cloning the privileged planner falls short.

    python -m experiments.kim_student labels [--episodes 60] OVERRIDES...
    python -m experiments.kim_student collect --student ddpg_kim_dag [--episodes 400] [--out FILE] OVERRIDES...
    python -m experiments.kim_student fit [--input lidar|state] [--steer-weight 1] [--data FILE] OVERRIDES...
    python -m experiments.kim_student drive [--input lidar|state] [--data FILE] evaluate.kim.seed=77 OVERRIDES...
    python -m experiments.kim_student dagger [--input lidar|state] [--rounds 2] [--episodes 150] evaluate.kim.seed=77
    python -m experiments.kim_student compare [--students student|dagger2] evaluate.kim.seed=77

``labels``: the planner drives training-distribution episodes (the demonstrations' stream) and, at every step, a
second planner plans from scratch, as a DAgger label does; counts the labels that go straight on, steer now, or
plan a steering manoeuvre that starts later (and so say "straight on" now).

``collect``: a trained cloned student (``agent.variant`` = ``--student``, its ``experiment`` and ``seed`` from the
overrides) drives ``--episodes`` fresh training-distribution episodes (``KIM_STUDENT_SCENARIOS``, apart from the
training's) and, at every step, records what it sees (the LIDAR view), the true state in its frame
(``true_state``), the planner's from-scratch label and its own action. Prints how often the label steers and how
often the student follows, and writes an ``.npz``.

``fit``: clones a fresh actor (the agent's network, ``agent.*`` overrides apply) on the first 80 % of the collected
episodes, from the LIDAR view or from the true state, and reports on the last 20 %: the mean squared error, and
where the label steers, how often the actor steers the same way. Settles whether the view or the teacher limits
the student: a student that sees the true state does no better if the teacher's choices are what it cannot copy.

``drive``: the same fit on all the collected episodes, then the fitted actor drives the evaluation's bank
(``evaluate.kim.*``; give the validation draw's seed, 77) in closed loop, beside straight-line braking: whether a
student with perfect perception, taught the same way, avoids more than one that sees the LIDAR.

``dagger``: from the collected episodes, ``--rounds`` DAgger rounds of the fitted student (each drives
``--episodes`` fresh episodes, labelled by the planner), then the last fit drives the bank as ``drive`` does.

``compare``: the seeds of ``drive`` (``--students student``) or ``dagger`` (``dagger2``) pooled per view, from the
per-trial files they wrote beside ``--data``, and the paired test between the two views.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from envs.kim import SCENARIOS, kim_action, kim_action_for
from envs.streams import KIM_DEMO_SCENARIOS, KIM_STUDENT_SCENARIOS
from worldmodel import stats
from worldmodel.artifacts import AgentId
from worldmodel.common import set_threads
from worldmodel.config import compose
from worldmodel.families.kim import system as kim
from worldmodel.models.ddpg import DDPG

HELD_OUT = 0.2


def steering(labels: np.ndarray) -> np.ndarray:
    """-1, 0 or 1 per Kim action: which way it steers (beyond ``kim.STEERING_LABEL``)."""
    return np.sign(labels[:, 1]) * (np.abs(labels[:, 1]) > kim.STEERING_LABEL)


def true_state(env) -> np.ndarray:
    """The state a perfect perception would give, in the ego's frame: its speed / 20 m/s, lateral position / 5 m
    and heading; for every car slot its position / 30 m, velocity relative to the ego / 20 m/s, heading (cos, sin)
    and whether it is in the scene (zeros when not); and the scenario's kind, one-hot."""
    ego, cars = env.ego, env.actors
    c, s = np.cos(-ego.psi), np.sin(-ego.psi)
    rotate = np.array([[c, -s], [s, c]])
    active = cars.car_active[:, None].astype(np.float64)
    position = (cars.car_xy - [ego.x, ego.y]) @ rotate.T / 30.0
    velocity = (cars.car_vel - [ego.v * np.cos(ego.psi), ego.v * np.sin(ego.psi)]) @ rotate.T / 20.0
    heading = cars.car_heading - ego.psi
    slots = np.concatenate([position, velocity, np.cos(heading)[:, None], np.sin(heading)[:, None], active], 1)
    kind = [float(env.scenario.scenario == k) for k in SCENARIOS]
    return np.concatenate([[ego.v / 20.0, ego.y / 5.0, ego.psi], (slots * active).ravel(), kind]).astype(np.float32)


def labels(cfg, episodes: int) -> None:
    env = kim.family_env(cfg, "kim_unaware")
    drive, label = kim.teacher(cfg), kim.teacher(cfg)
    counts, avoided = {"straight on": 0, "steer now": 0, "steer later": 0}, 0
    for i in tqdm(range(episodes), desc="planner episodes", unit="episode"):
        env.reset(options={"scenario": kim.training_scenario(cfg, KIM_DEMO_SCENARIOS, i)})
        for p in (drive, label):
            p.reset()
            p.bind(env)
        while True:
            label.plan = None  # from scratch, as a DAgger label
            label.act(None, None)
            m = label.plan.manoeuvre
            counts["straight on" if not m.steer else ("steer later" if m.delay else "steer now")] += 1
            _, _, terminated, truncated, _ = env.step(drive.act(None, None))
            if terminated or truncated:
                break
        avoided += int(not env.collisions)
    total = sum(counts.values())
    print(", ".join(f"{k}: {v} ({100 * v / total:.1f} %)" for k, v in counts.items()))
    print(f"the planner avoided {100 * avoided / episodes:.1f} % of {episodes} episodes")


def record(cfg, agent, source: str, see, stream: tuple, episodes: int, desc: str = "student episodes") -> dict:
    """The student (``agent``, reading the LIDAR ``see`` or ``true_state`` by ``source``) drives ``episodes``
    training-distribution episodes of ``stream``; at every step the planner labels the state from scratch. Both
    views are recorded, whichever the student reads."""
    env = kim.family_env(cfg, "kim_unaware")
    planner = kim.teacher(cfg)
    view, state, label, action, episode, collided = [], [], [], [], [], []
    for e in tqdm(range(episodes), desc=desc, unit="episode"):
        env.reset(options={"scenario": kim.training_scenario(cfg, *stream, e)})
        planner.reset()
        planner.bind(env)
        see.reset(None)
        n = 0
        while True:
            planner.plan = None
            label.append(kim_action_for(planner.act(None, None), env.ego.v))
            view.append(see(env))
            state.append(true_state(env))
            a = agent.act(view[-1] if source == "lidar" else state[-1], explore=False)
            see.note_action(a)
            action.append(a)
            n += 1
            _, _, terminated, truncated, _ = env.step(kim_action(a, env.ego.v))
            if terminated or truncated:
                break
        episode += [e] * n
        collided += [bool(env.collisions)] * n
    env.close()
    return {
        "view": np.asarray(view, np.float32),
        "state": np.asarray(state, np.float32),
        "label": np.asarray(label, np.float32),
        "action": np.asarray(action, np.float32),
        "episode": np.asarray(episode),
        "collided": np.asarray(collided),
    }


def collect(cfg, episodes: int, out: Path) -> None:
    policy, _ = kim.load_policy(cfg, AgentId.of(cfg))
    data = record(cfg, policy.agent, "lidar", policy.see, (KIM_STUDENT_SCENARIOS,), episodes)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **data)
    agreement("the student", data["action"], data["label"])
    side, ep = steering(data["label"]), data["episode"]
    crashed = [e for e in np.unique(ep) if data["collided"][ep == e][0]]
    steered = sum(bool(np.any(side[ep == e] != 0)) for e in crashed)
    print(f"{len(crashed)} of {episodes} student episodes end in a collision; in {steered} the planner would steer")
    runs = [len(list(g)) for e in np.unique(ep) for k, g in itertools.groupby(side[ep == e]) if k != 0]
    both = sum(len(set(side[(ep == e) & (side != 0)])) > 1 for e in np.unique(ep))
    print(
        f"{len(runs)} runs of steering labels, {100 * np.mean(np.array(runs) == 1):.0f} % one step long; "
        f"labels steer both ways in {both} episodes"
    )
    print(f"wrote {out}")


def agreement(who: str, actions: np.ndarray, targets: np.ndarray) -> None:
    side = steering(targets)
    steers = side != 0
    same = np.mean(steering(actions)[steers] == side[steers])
    false = np.mean(steering(actions)[~steers] != 0)
    print(
        f"{who}: where the label steers ({100 * steers.mean():.1f} % of {len(side)} steps), the same way on "
        f"{100 * same:.1f} % (|steer| {np.abs(actions[steers, 1]).mean():.2f} against the label's "
        f"{np.abs(targets[steers, 1]).mean():.2f}); where it does not, it steers on {100 * false:.1f} %"
    )


def fit(cfg, data: dict, source: str, steer_weight: float, steps: int = 6000, held_out_share: float = HELD_OUT):
    """A fresh actor cloned on the episodes before the last ``held_out_share``, reporting on those (if any)."""
    x, y, ep = data["view" if source == "lidar" else "state"], data["label"], data["episode"]
    held_out = ep >= np.quantile(np.unique(ep), 1.0 - held_out_share) if held_out_share else np.zeros(len(ep), bool)
    hp = kim.ddpg_config(cfg)
    if source == "state":
        hp = dataclasses.replace(hp, lidar_scans=0)  # the true state goes straight into the MLP
    agent = DDPG(x.shape[1], 2, hp, int(cfg.seed))
    xs, ys = torch.from_numpy(x[~held_out]), torch.from_numpy(y[~held_out])
    weights = torch.where(ys[:, 1].abs() > kim.STEERING_LABEL, steer_weight, 1.0)
    rng = np.random.default_rng(int(cfg.seed))
    print(f"{source}: {int((~held_out).sum())} training steps, {int(held_out.sum())} held out")
    for k in range(steps):
        idx = torch.from_numpy(rng.integers(0, len(xs), size=hp.batch_size))
        agent.clone(xs[idx], ys[idx], weights[idx])
        if held_out.any() and (k + 1) % (steps // 4) == 0:
            with torch.no_grad():
                a = agent.actor(torch.from_numpy(x[held_out])).numpy()
            mse = ((a - y[held_out]) ** 2).sum(-1).mean()
            agreement(f"after {k + 1} minibatches (held-out squared error {mse:.3f})", a, y[held_out])
    return agent


class TrueStatePolicy:
    """A fitted actor that reads ``true_state``: the student with perfect perception, behind the policy interface."""

    def __init__(self, name: str, agent):
        self.name, self.agent = name, agent

    def reset(self, seed=None) -> None:
        pass

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        return kim_action(self.agent.act(true_state(self.env), explore=False), self.env.ego.v)


def lidar_observer(cfg, data: dict):
    see = kim.observer(cfg, "kim_unaware")
    if see.dim != data["view"].shape[1]:
        raise SystemExit(f"the data holds views of {data['view'].shape[1]} numbers, agent.* gives {see.dim}")
    return see


def drive(cfg, agent, source: str, name: str, out_dir: Path) -> None:
    """``agent`` drives the evaluation's bank beside straight-line braking (``beside_braking``)."""
    see = kim.observer(cfg, "kim_unaware")
    student = TrueStatePolicy(name, agent) if source == "state" else kim.LidarPolicy(name, agent, see, int(cfg.seed))
    beside_braking(cfg, student, out_dir)


def beside_braking(cfg, policy, out_dir: Path) -> None:
    """``policy`` and straight-line braking drive the evaluation's bank (``evaluate.kim.*``); prints both and the
    paired test, and writes each one's per-trial avoidance and ISS to ``drive_<name>_draw<seed>.csv``."""
    from envs import StraightLineBraking

    specs, env = kim.bank(cfg.evaluate.kim), kim.family_env(cfg, "kim_unaware")
    rows = {p.name: kim.run_policy(env, p, specs, int(cfg.seed)) for p in (StraightLineBraking(), policy)}
    env.close()
    iss = {name: np.array([r["iss_kmh"] for r in rs]) for name, rs in rows.items()}
    for name, rs in rows.items():
        avoided = sum(r["avoided"] for r in rs)
        low, high = stats.wilson(avoided, len(rs))
        print(
            f"{name}: avoided {100 * avoided / len(rs):.1f} % [{low:.0f}, {high:.0f}] of {len(rs)} trials "
            f"(draw {cfg.evaluate.kim.seed}); injury {-iss[name].mean():.2f}"
        )
    p = stats.paired_permutation_p(iss[policy.name], iss["braking"])
    print(f"paired p on per-trial ISS against braking: {p:.4f}")
    for name, rs in rows.items():
        out = out_dir / f"drive_{name}_draw{cfg.evaluate.kim.seed}.csv"
        np.savetxt(out, np.c_[[r["avoided"] for r in rs], iss[name]], delimiter=",", header="avoided,iss_kmh")
        print(f"wrote {out}")


def dagger(cfg, data: dict, source: str, steer_weight: float, rounds: int, episodes: int, out_dir: Path) -> None:
    """DAgger from the collected episodes: ``rounds`` times, fit on everything so far, let that student drive
    ``episodes`` fresh episodes (a stream per round, apart from the collection's) and add the planner's labels;
    then fit once more and drive the bank. Shows whether a student of either view gains from its own states."""
    see = lidar_observer(cfg, data) if source == "lidar" else kim.observer(cfg, "kim_unaware")
    for r in range(1, rounds + 1):
        agent = fit(cfg, data, source, steer_weight, held_out_share=0.0)
        more = record(cfg, agent, source, see, (KIM_STUDENT_SCENARIOS, int(cfg.seed), r), episodes, f"round {r}")
        more["episode"] = more["episode"] + int(data["episode"].max()) + 1
        print(f"round {r}: the student avoided {100 * (1 - np.mean(_ends(more))):.1f} % of its {episodes} episodes")
        data = {k: np.concatenate([data[k], more[k]]) for k in data}
    agent = fit(cfg, data, source, steer_weight, held_out_share=0.0)
    drive(cfg, agent, source, f"dagger{rounds}_{source}_seed{int(cfg.seed)}", out_dir)


def compare(cfg, students: str, out_dir: Path) -> None:
    draw = cfg.evaluate.kim.seed
    pooled = {}
    for source in ("state", "lidar"):
        files = sorted(out_dir.glob(f"drive_{students}_{source}_seed*_draw{draw}.csv"))
        if not files:
            raise SystemExit(
                f"no drive_{students}_{source}_seed*_draw{draw}.csv in {out_dir}: run drive or dagger first"
            )
        pooled[source] = np.concatenate([np.loadtxt(f, delimiter=",", ndmin=2) for f in files])
        avoided, iss = pooled[source][:, 0], pooled[source][:, 1]
        low, high = stats.wilson(int(avoided.sum()), len(avoided))
        print(
            f"{students} {source}, {len(files)} seeds pooled: avoided {100 * avoided.mean():.1f} % [{low:.0f}, "
            f"{high:.0f}] of {len(avoided)}; injury {-iss.mean():.2f}"
        )
    state, lidar = pooled["state"], pooled["lidar"]
    p = stats.paired_permutation_p(state[:, 1], lidar[:, 1])
    print(
        f"paired by seed and trial, ISS state against LIDAR: p = {p:.4f}; only the state student avoids "
        f"{100 * np.mean((state[:, 0] == 1) & (lidar[:, 0] == 0)):.1f} %, only the LIDAR one "
        f"{100 * np.mean((state[:, 0] == 0) & (lidar[:, 0] == 1)):.1f} %"
    )


def _ends(data: dict) -> np.ndarray:
    """Per episode, whether it ended in a collision."""
    ep = data["episode"]
    return np.array([data["collided"][ep == e][0] for e in np.unique(ep)])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("labels", "collect", "fit", "drive", "dagger", "compare"))
    parser.add_argument("--episodes", type=int, default=None, help="labels: 60; collect: 400; dagger: 150 per round")
    parser.add_argument("--student", default="ddpg_kim_dag", help="collect: the cloned student's agent.variant")
    parser.add_argument("--out", "--data", dest="data", type=Path, default=Path("runs/kim_student/steps.npz"))
    parser.add_argument("--input", choices=("lidar", "state"), default="lidar", help="fit, drive, dagger: its view")
    parser.add_argument("--steer-weight", type=float, default=1.0, help="as agent.kim.bc_steer_weight")
    parser.add_argument("--rounds", type=int, default=2, help="dagger: rounds before the last fit")
    parser.add_argument("--students", default="student", help="compare: student (drive) or dagger<rounds>")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=kimfd scale=quick seed=0")
    args = parser.parse_intermixed_args(argv)  # options may follow the overrides
    overrides = ["agent=ddpg_kim", *args.overrides]
    if args.command == "collect":
        overrides.append(f"agent.variant={args.student}")
    cfg = compose("train_agent", overrides)
    set_threads(1)
    if args.command == "labels":
        labels(cfg, args.episodes or 60)
        return
    if args.command == "collect":
        collect(cfg, args.episodes or 400, args.data)
        return
    if args.command == "compare":
        compare(cfg, args.students, args.data.parent)
        return
    data = dict(np.load(args.data))
    if args.input == "lidar":
        lidar_observer(cfg, data)  # fail before any fitting if the views do not match
    if args.command == "fit":
        fit(cfg, data, args.input, args.steer_weight)
    elif args.command == "drive":
        agent = fit(cfg, data, args.input, args.steer_weight, held_out_share=0.0)
        drive(cfg, agent, args.input, f"student_{args.input}_seed{int(cfg.seed)}", args.data.parent)
    else:
        dagger(cfg, data, args.input, args.steer_weight, args.rounds, args.episodes or 150, args.data.parent)


if __name__ == "__main__":
    main()
