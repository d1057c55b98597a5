"""Scenario family ``chae`` (envs/chae.py) on the real simulator: replay, trigger, termination, reward, state and
the physics band that braking at the trigger gives."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from envs import UrbanCollisionEnv, rollout
from envs.chae import (
    ALPHA,
    BETA,
    ETA,
    LAMBDA,
    V_INIT_RANGE,
    ChaeSpec,
    ClosingSpeedBraking,
    LatestSafeBraking,
    PedestrianHistory,
    brake_action,
    sample_chae,
)
from envs.families import spec_from_dict
from envs.policies import ConstantAction


@pytest.fixture(scope="module")
def env():
    return UrbanCollisionEnv(camera=False, step_s=0.1, reward="chae")


def smoke_dqn_chae(root, *extra):
    """agent=dqn_chae at smoke scale under ``root``, learning from step 40, so that the network changes within
    smoke's 12 episodes (and between validations)."""
    from worldmodel.config import compose

    return compose(
        "train_agent",
        [
            f"paths.data_root={root}/data",
            f"paths.runs_root={root}/runs",
            "experiment=t",
            "scale=smoke",
            "threads=1",
            "agent=dqn_chae",
            "agent.dqn.warmup_steps=40",
            *extra,
        ],
    )


def test_specs_validate_and_round_trip():
    spec = sample_chae(np.random.default_rng(0))
    assert spec_from_dict(spec.to_dict()) == spec and spec.to_dict()["family"] == "chae"
    with pytest.raises(ValueError, match="v_init"):
        ChaeSpec(seed=1, ttc=2.0, v_init=-1.0)
    with pytest.raises(ValueError, match="family"):
        spec_from_dict({**spec.to_dict(), "family": "nope"})
    with pytest.raises(ValueError, match="unknown chae scenario fields"):
        spec_from_dict({**spec.to_dict(), "speed": 3.0})


def test_replays_bit_identically(env):
    spec = ChaeSpec(seed=7, ttc=1.2, v_init=12.0, v_ped=2.5, far_side=True)
    first, again = (json.dumps(rollout(env, LatestSafeBraking(), spec).outcome) for _ in range(2))
    assert first == again


def test_the_pedestrian_starts_when_the_bumper_passes_the_trigger(env):
    """At constant speed the bumper passes p_trig = (5 - TTC) v after 5 - TTC seconds, mid-step here; from then the
    pedestrian is exactly where a walk begun at that instant puts it, and the bumper reaches its x TTC later."""
    spec = ChaeSpec(seed=1, ttc=2.03, v_init=10.0, v_ped=3.0)
    env.reset(options={"scenario": spec})
    start_y, t_trig = env.actors.ped_xy[0, 1], 5.0 - spec.ttc
    for k in range(1, 40):
        env.step([0.0, 0.0])
        t = k * 0.1
        expected = start_y + spec.v_ped * max(0.0, t - t_trig)  # near side: walks towards +y
        assert env.actors.ped_xy[0, 1] == pytest.approx(expected, abs=1e-9), t
    front = env.ego.x + env.params.length / 2
    assert (env.family_state.ped_x - front) / spec.v_init == pytest.approx(5.0 - 3.9)


def test_termination_cases(env):
    keep, brake = ConstantAction([0.0, 0.0]), ConstantAction(brake_action(0))
    # no braking: the bumper passes the safety line while the pedestrian crosses, 3 m short of it
    o = rollout(env, keep, ChaeSpec(seed=1, ttc=1.5, v_init=10.0)).outcome
    assert o["end"] == "bump" and o["gap_to_pedestrian"] == pytest.approx(3.0, abs=1.0)
    # Scenario 2: braking is an unnecessary stop, keeping on passes
    stays = ChaeSpec(seed=1, ttc=2.0, v_init=10.0, crosses=False)
    assert rollout(env, brake, stays).outcome["end"] == "stop"
    assert rollout(env, keep, stays).outcome["end"] == "pass"
    # slow car, early trigger, fast pedestrian: it is across before the car arrives
    assert rollout(env, keep, ChaeSpec(seed=1, ttc=4.0, v_init=3.0, v_ped=4.0)).outcome["end"] == "cross"


def test_chae_reward_matches_eq_8_by_hand(env):
    spec = ChaeSpec(seed=1, ttc=1.6, v_init=15.0)  # still crossing when the car arrives
    env.reset(options={"scenario": spec})
    dx = env.family_state.ped_x - (env.ego.x + env.params.length / 2)
    v0 = env.ego.v
    _, reward, _, _, info = env.step(brake_action(1))
    # the bumper moved during the step: dx is read after it
    dx = env.family_state.ped_x - (env.ego.x + env.params.length / 2)
    assert reward == pytest.approx(-(ALPHA * dx**2 + BETA) * (v0 - env.ego.v))
    assert v0 - env.ego.v == pytest.approx(5.9 * 0.1)
    assert info["reward_r2"] == 0.0 and info["reward_chae"] == reward
    env.reset(options={"scenario": spec})
    total = 0.0
    while True:
        _, reward, terminated, truncated, info = env.step([0.0, 0.0])
        total += reward
        if terminated or truncated:
            break
    assert info["outcome"]["end"] == "bump"
    assert reward == pytest.approx(-(ETA * 15.0**2 + LAMBDA)) and total == pytest.approx(reward)


def test_pedestrian_history_is_15_values_oldest_first(env):
    view = PedestrianHistory(noise_m=0.0)
    env.reset(options={"scenario": ChaeSpec(seed=1, ttc=2.0, v_init=10.0)})
    view.reset(0)
    first = view(env)
    assert first.shape == (15,) and np.allclose(first.reshape(5, 3), first[:3])  # the first state, repeated
    for _ in range(6):
        env.step([0.0, 0.0])
        state = view(env).reshape(5, 3)
    assert np.allclose(np.diff(state[:, 0]), -1.0)  # the gap shrinks by v * 0.1 s per step
    assert np.allclose(state[:, 2], 10.0)


def test_braking_at_the_trigger_lands_in_the_physics_band(env):
    """The physics check: full braking exactly at the trigger bumps in 37.3 / 3.1 / 0 / 0 % at TTC 0.9 /
    1.1 / 1.3 / 1.5 s (v ~ U(10, 60) km/h), and in 76.5 / 12.1 / 0.46 / 0 % a step of 0.1 s later. Deciding once per
    step, the privileged policies react 0-0.1 s late, so they must land inside that band."""
    band = {0.9: (37.3, 76.5), 1.1: (3.1, 12.1), 1.3: (0.0, 0.46), 1.5: (0.0, 0.0)}
    for policy in (LatestSafeBraking(),):
        for ttc, (lo, hi) in band.items():
            rng = np.random.default_rng(int(ttc * 10))
            n, bumps = 100, 0
            for i in range(n):
                v = float(rng.uniform(*V_INIT_RANGE))
                spec = ChaeSpec(seed=i, ttc=ttc, v_init=v, v_ped=float(rng.uniform(2, 4)), far_side=i % 2 == 1)
                bumps += rollout(env, policy, spec).outcome["end"] == "bump"
            rate = 100 * bumps / n
            slack = 100 * 2.5 * np.sqrt(max(lo, 1) / 100 * (1 - max(lo, 1) / 100) / n)  # sampling noise
            assert lo - slack <= rate <= hi + slack, (policy.name, ttc, rate)


def test_the_closing_speed_rule_reads_the_agents_state_and_brakes_only_for_a_walking_pedestrian(env):
    """``ClosingSpeedBraking`` sees what dqn_chae sees. Its slope by hand: |dy| 3.0, 2.7, ..., 1.8 m at 0.1 s steps
    is 3 m/s closing; without noise it never brakes for a pedestrian who stays, and for one who walks it brakes
    within the readings a 1 m/s threshold needs (the line over 5 readings passes 1 m/s at the 2nd or 3rd moving one)."""
    rule = ClosingSpeedBraking(threshold_ms=1.0, readings=5, noise_m=0.0)
    rule.bind(env)
    history = np.array([[20.0 - k, -(3.0 - 0.3 * k), 8.0] for k in range(5)]).ravel()  # on the right, closing
    assert rule.closing_speed(history) == pytest.approx(3.0)
    assert rule.closing_speed(np.tile([20.0, 3.0, 8.0], 5)) == pytest.approx(0.0, abs=1e-12)

    stays = ChaeSpec(seed=3, ttc=1.5, v_init=10 / 3.6, crosses=False)
    o = rollout(env, rule, stays).outcome
    assert o["end"] == "pass" and not o["bumped"]

    walks = ChaeSpec(seed=3, ttc=1.5, v_init=10 / 3.6, v_ped=2.0)  # the corner the learned ensembles bump in
    trace = []  # (the pedestrian has started after the step, the step's pedal)

    def record(obs, action, reward, info):
        trace.append((env.family_state.started, action[1]))

    rollout(env, rule, walks, on_step=record)
    first_started = next(k for k, (started, _) in enumerate(trace) if started)
    first_brake = next(k for k, (_, pedal) in enumerate(trace) if pedal < 0)
    assert 0 < first_brake - first_started <= 3, (first_started, first_brake)
    assert all(pedal == -1.0 for _, pedal in trace[first_brake:])  # braking fully, to the stop
    assert rollout(env, rule, walks).outcome["end"] == "stop"

    with pytest.raises(ValueError, match="readings"):
        ClosingSpeedBraking(readings=1)
    with pytest.raises(ValueError, match="threshold_ms"):
        ClosingSpeedBraking(threshold_ms=0.0)


def test_evaluation_records_the_bump_and_runs_on_to_measure_contact():
    """end_on_bump=False (the evaluation's env) flags the same bump and lets the episode run on, so that contact and
    impact speed are measured; Chae's training env ends at it."""
    hold = np.zeros(2, dtype=np.float32)
    spec = ChaeSpec(seed=0, ttc=1.0, v_init=12.0, v_ped=3.0)
    ends = {}
    for end_on_bump in (True, False):
        env = UrbanCollisionEnv(camera=False, family="chae", step_s=0.1, family_options={"end_on_bump": end_on_bump})
        env.reset(options={"scenario": spec})
        steps = 0
        while True:
            _, _, terminated, truncated, info = env.step(hold)
            steps += 1
            if terminated or truncated:
                break
        ends[end_on_bump] = (info["outcome"], steps)
        env.close()
    (trained, n_trained), (evaluated, n_evaluated) = ends[True], ends[False]
    assert trained["end"] == "bump" and trained["bumped"] == 1 and trained["pedestrian_collision"] == 0
    assert evaluated["bumped"] == 1 and evaluated["end"] != "bump" and n_evaluated > n_trained
    assert evaluated["pedestrian_collision"] == 1 and evaluated["speed_at_collision"] == pytest.approx(12.0)


def test_checkpoint_selection_by_chaes_metrics():
    """best.pt's rule (agent.chae.select): among checkpoints bumping in <= max_bump % at every TTC, fewest needless
    stops; if none is that safe, the one bumping least; the earliest wins a tie."""
    from worldmodel.families.chae.system import selected

    def score(episode, bump, stops):
        return {"episode": episode, "max_bump_rate": bump, "unnecessary_stop_rate": stops}

    runs = [score(250, 0.5, 30.0), score(500, 2.0, 1.0), score(750, 1.0, 12.0), score(1000, 0.0, 12.0)]
    assert selected(runs, 1.0)["episode"] == 750  # 500 stops least but bumps too often
    assert selected(runs, 2.0)["episode"] == 500
    assert selected(runs, 0.0)["episode"] == 1000
    unsafe = [score(250, 3.0, 0.0), score(500, 1.5, 40.0), score(750, 1.5, 20.0)]
    assert selected(unsafe, 1.0)["episode"] == 750
    assert selected([], 1.0) is None


@pytest.fixture(scope="module")
def kept_run(tmp_path_factory):
    """A smoke dqn_chae run that validated every 4 episodes and kept each validated checkpoint
    (agent.chae.select.keep), at its planned 12 episodes (no extension)."""
    from worldmodel import train_agent

    keep = ("agent.chae.select.keep=true", "agent.chae.select.extend_blocks=0")
    chosen = smoke_dqn_chae(tmp_path_factory.mktemp("chosen"), *keep)
    train_agent.run(chosen)
    return chosen


def test_checkpoint_selection_leaves_training_alone_and_evaluation_loads_the_chosen_one(kept_run, tmp_path):
    """Validating greedily between episodes draws nothing from the learner's RNG, so last.pt is what a run without
    selection ends with; best.pt holds the chosen episode's network, and load_policy returns it; every validated
    checkpoint is kept when asked. Choosing on the evaluation's own draw is refused."""
    import torch

    from worldmodel import train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.common import StageError
    from worldmodel.families.chae.system import load_policy, validated_path

    cfg = smoke_dqn_chae
    chosen, plain = kept_run, cfg(tmp_path / "plain", "agent.chae.select.every=0")
    train_agent.run(plain)
    agent = AgentId.of(chosen)
    load = lambda c, which: torch.load(agent.dir(c) / f"{which}.pt", weights_only=False)  # noqa: E731
    last, last_plain, best = load(chosen, "last"), load(plain, "last"), load(chosen, "best")
    assert not (agent.dir(plain) / "best.pt").exists() and not (agent.dir(plain) / "validated").exists()
    for name, w in last["agent"]["q_network"].items():
        assert torch.equal(w, last_plain["agent"]["q_network"][name]), name
    scores = last["curve"]["validation"]
    assert [s["episode"] for s in scores] == [4, 8, 12]  # smoke: every 4 episodes from a quarter of 12
    assert sorted(p.name for p in (agent.dir(chosen) / "validated").iterdir()) == [
        f"episode{e:05d}.pt" for e in (4, 8, 12)
    ]
    kept = torch.load(validated_path(agent.dir(chosen), best["episode"]), weights_only=False)
    for name, w in best["agent"]["q_network"].items():
        assert torch.equal(w, kept["agent"]["q_network"][name]), name
    metrics = json.loads((agent.dir(chosen) / "metrics.json").read_text())
    assert best["episode"] == metrics["selected"]["episode"] in (4, 8, 12)
    policy = load_policy(chosen, agent)
    for name, w in policy.agent.q_network.state_dict().items():
        assert torch.equal(w, best["agent"]["q_network"][name]), name
    if best["episode"] != 12:  # then last.pt's network has moved on, and was not the one loaded
        moved = [not torch.equal(w, last["agent"]["q_network"][n]) for n, w in best["agent"]["q_network"].items()]
        assert last["episode"] == 12 and any(moved)
    with pytest.raises(StageError, match="evaluate.chae.seed"):
        train_agent.run(cfg(tmp_path / "clash", "agent.chae.select.seed=2017"))


def test_rescoring_keeps_the_checkpoint_with_the_most_room_under_both_bars():
    """agent.chae.select.rescore's rule (and experiments.chae_reselect's): candidates inside both bars on training's
    draw, the fewest bumps at TTC 1.5 s first; then the smallest max(bumps / 1 %, stops / 5 %) on the larger draw, the
    later on a tie."""
    from worldmodel.families.chae.system import rescore_choice, rescore_shortlist, room

    def trained(episode, corner, worst, stops):
        bumps = {"bump_rate": {"1.5": corner}, "max_bump_rate": worst}
        return {"episode": episode, **bumps, "unnecessary_stop_rate": stops}

    scores = [trained(1500, 0.0, 0.0, 6.0), trained(1750, 0.5, 0.5, 1.0), trained(2000, 0.0, 1.0, 2.0)]
    scores += [trained(2250, 1.5, 1.5, 0.0), trained(2500, 0.0, 0.5, 2.0), trained(2750, 1.0, 1.0, 0.0)]
    # 1500 stops too often and 2250 bumps too often; among the rest, 0 % at the corner first, fewer stops, later
    assert [s["episode"] for s in rescore_shortlist(scores, 3, 1.0, 5.0, 1.5)] == [2500, 2000, 1750]
    assert rescore_shortlist(scores[:1], 3, 1.0, 5.0, 1.5) == []
    assert [s["episode"] for s in rescore_shortlist(scores[:1], 3, 1.0, 10.0, 1.5)] == [1500]
    assert room({"bump_rate": 0.6, "unnecessary_stop_rate": 4.0}, 1.0, 5.0) == pytest.approx(0.8)

    def rescored(episode, bumps, stops):
        return {"episode": episode, "bump_rate": bumps, "unnecessary_stop_rate": stops}

    three = [rescored(1750, 0.4, 4.5), rescored(2000, 0.8, 1.0), rescored(2500, 0.6, 0.0)]
    assert rescore_choice(three, 1.0, 5.0)["episode"] == 2500
    two = [rescored(1750, 0.4, 0.0), rescored(2000, 0.0, 2.0)]
    assert rescore_choice(two, 1.0, 5.0)["episode"] == 2000  # 0.4 each: the later
    assert rescore_choice([], 1.0, 5.0) is None


def test_rescoring_at_the_end_of_training_makes_the_chosen_kept_checkpoint_best(tmp_path):
    """agent.chae.select.rescore: the shortlisted kept checkpoints drive the rescoring draw after the last episode, and
    best.pt is the chosen one's file; without keep, or on the evaluation's draw, it is refused."""
    from worldmodel import train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.common import StageError
    from worldmodel.families.chae.system import validated_path

    # smoke's 12 episodes learn neither bar: let every checkpoint be a candidate
    bars = ("agent.chae.select.max_bump=100", "agent.chae.select.max_stops=100")
    rescore = ("agent.chae.select.keep=true", *bars, "agent.chae.select.rescore=2")
    draw = ("agent.chae.select.rescore_trials=3", "agent.chae.select.rescore_ttcs=[1.5,3.1]")
    cfg = smoke_dqn_chae(tmp_path, *rescore, *draw)
    train_agent.run(cfg)
    run = AgentId.of(cfg).dir(cfg)
    metrics = json.loads((run / "metrics.json").read_text())
    record = metrics["rescored"]
    assert (record["seed"], record["trials"], record["ttc"], record["ttcs"]) == (98, 3, 1.5, [1.5, 3.1])
    assert len(record["rescored"]) == 2 and record["chosen"] in record["rescored"]
    for r in record["rescored"]:
        assert set(r["bump_rates"]) == {"1.5", "3.1"} and r["bump_rate"] == max(r["bump_rates"].values())
        for rate in r["bump_rates"].values():
            assert rate * 3 / 100 == pytest.approx(round(rate * 3 / 100))  # counts out of 3
    assert metrics["selected"]["episode"] == record["chosen"]["episode"]
    chosen = validated_path(run, record["chosen"]["episode"]).read_bytes()
    assert (run / "best.pt").read_bytes() == chosen
    with pytest.raises(StageError, match="keep=true"):
        no_keep = ("agent.chae.select.keep=false", "agent.chae.select.rescore=2")
        train_agent.run(smoke_dqn_chae(tmp_path / "no_keep", *no_keep))
    with pytest.raises(StageError, match="select.rescore_ttcs"):
        train_agent.run(smoke_dqn_chae(tmp_path / "bad_ttcs", *rescore, "agent.chae.select.rescore_ttcs=[]"))
    with pytest.raises(StageError, match="rescore_seed"):
        train_agent.run(smoke_dqn_chae(tmp_path / "clash", *rescore, "agent.chae.select.rescore_seed=2017"))


def test_training_goes_on_in_blocks_until_the_rescoring_finds_a_member_inside_both_bars(tmp_path):
    """agent.chae.select.extend: after the planned episodes, a run whose rescoring chose nothing inside both bars trains
    another block, validating and keeping as before, and is rescored again, until a member is found or the blocks
    run out; with bars everything passes, the run ends at its planned length. Bad settings are refused."""
    from worldmodel import train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.common import StageError
    from worldmodel.families.chae.system import first_target

    def trained(root, *bars):
        cfg = smoke_dqn_chae(root, "agent.chae.select.rescore=2", "agent.chae.select.rescore_trials=2", *bars)
        sel = cfg.agent.chae.select
        assert (sel.extend, sel.extend_blocks) == (4, 2)  # smoke's block, the preset's cap
        train_agent.run(cfg)
        run = AgentId.of(cfg).dir(cfg)
        return json.loads((run / "metrics.json").read_text()), run

    metrics, run = trained(tmp_path / "strict", "agent.chae.select.max_bump=0", "agent.chae.select.max_stops=0")
    gates = metrics["gates"]
    assert 1 <= len(gates) <= 3 and not any(g["member"] for g in gates[:-1])
    assert gates[-1]["member"] or len(gates) == 3  # stopped by a member, or after the last block
    assert metrics["episodes"] == 12 + 4 * (len(gates) - 1) == gates[-1]["episode"] == 12 + metrics["extended"]
    assert [g["episode"] for g in gates] == list(range(12, metrics["episodes"] + 1, 4))
    validated = [s["episode"] for s in metrics["curve"]["validation"]]
    assert validated == list(range(4, metrics["episodes"] + 1, 4)) and len(metrics["curve"]["end"]) == validated[-1]
    assert sorted(p.name for p in (run / "validated").iterdir()) == [f"episode{e:05d}.pt" for e in validated]
    if metrics["rescored"]["chosen"] is not None:
        assert (run / "best.pt").read_bytes() == (
            run / "validated" / f"episode{metrics['selected']['episode']:05d}.pt"
        ).read_bytes()

    loose, _ = trained(tmp_path / "loose", "agent.chae.select.max_bump=100", "agent.chae.select.max_stops=100")
    assert loose["gates"] == [{"episode": 12, "member": True}] and loose["episodes"] == 12 and loose["extended"] == 0

    # a finished run without the extension, resumed with it, trains on exactly as one that had it from the start
    strict = ("agent.chae.select.rescore=2", "agent.chae.select.rescore_trials=2", "agent.chae.select.max_bump=0")
    once = ("agent.chae.select.max_stops=0", "agent.chae.select.extend_blocks=0")
    cfg = smoke_dqn_chae(tmp_path / "later", *strict, *once)
    train_agent.run(cfg)
    train_agent.run(smoke_dqn_chae(tmp_path / "later", *strict, "agent.chae.select.max_stops=0", "resume=true"))
    later = json.loads((AgentId.of(cfg).dir(cfg) / "metrics.json").read_text())
    assert later["curve"] == metrics["curve"] and later["gates"] == metrics["gates"]
    # a run resumed inside a block finishes it before it is rescored
    assert [first_target(e, 12, 4) for e in (0, 12, 13, 16, 17)] == [12, 12, 16, 16, 20] and first_target(
        13, 12, 0
    ) == 12

    with pytest.raises(StageError, match="select.extend"):
        train_agent.run(smoke_dqn_chae(tmp_path / "no_rescore", "agent.chae.select.rescore=0"))
    with pytest.raises(StageError, match="select.extend"):
        train_agent.run(smoke_dqn_chae(tmp_path / "odd_block", "agent.chae.select.extend=6"))


def test_reselection_copies_the_run_with_the_rescored_choice_as_best(kept_run, tmp_path):
    """On a run whose training-time scores are all inside both bars, the shortlisted kept checkpoints drive the new
    draw, the chosen one becomes the copy's best.pt, and the evaluation's loader reads it; the judging draws are
    refused."""
    import torch

    from experiments import chae_reselect
    from worldmodel import artifacts
    from worldmodel.artifacts import AgentId
    from worldmodel.families.chae.system import load_policy, rescore_choice, validated_path

    run = tmp_path / "t"
    shutil.copytree(kept_run.paths.runs, run)
    agent_dir = run / "agent_chae_dqn_chae/seed0"
    last = torch.load(agent_dir / "last.pt", weights_only=False)
    for s in last["curve"]["validation"]:  # smoke's 12 episodes never learn to pass: call them inside the bars
        s.update(bump_rate={"1.5": 0.0}, max_bump_rate=0.0, unnecessary_stop_rate=0.0)
    torch.save(last, agent_dir / "last.pt")
    record = artifacts.read_provenance(agent_dir)  # as if the run had written this last.pt
    artifacts.write_provenance(agent_dir, {**record, "outputs": artifacts.output_digests(agent_dir)})
    with pytest.raises(SystemExit, match="judging draw"):
        chae_reselect.main([str(run), "--seeds", "0", "--out", str(tmp_path / "no"), "--draw", "102"])
    out = tmp_path / "t_reselected"
    chae_reselect.main([str(run), "--seeds", "0", "--out", str(out), "--shortlist", "2", "--trials", "3"])
    record = json.loads((out / "agent_chae_dqn_chae/seed0/reselection.json").read_text())
    assert [r["episode"] for r in record["rescored"]] == [12, 8]  # all tie on training's draw: later first
    assert record["chosen"] == rescore_choice(record["rescored"], 1.0, 5.0)
    cfg = smoke_dqn_chae(tmp_path).copy()
    cfg.paths.runs = str(out)
    policy = load_policy(cfg, AgentId.of(cfg))
    kept = torch.load(validated_path(agent_dir, record["chosen"]["episode"]), weights_only=False)
    for name, w in policy.agent.q_network.state_dict().items():
        assert torch.equal(w, kept["agent"]["q_network"][name]), name


def test_seed_ensembles_act_on_the_mean_q_of_their_members_and_are_evaluated(tmp_path):
    """evaluate.chae.ensemble=2 with seeds 0 and 1 trained: one ensemble, greedy on the mean of the two chosen
    checkpoints' Q-values, driven through the same trials as every policy; with 3 per ensemble no group is complete,
    and 1 member is not an ensemble."""
    import csv

    from worldmodel import train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.common import StageError
    from worldmodel.config import compose, validate
    from worldmodel.families.chae import system as chae

    def cfg(stage, *extra):
        base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=e", "scale=smoke"]
        return compose(stage, [*base, "threads=1", "agent=dqn_chae", "agent.dqn.warmup_steps=40", *extra])

    for seed in (0, 1):
        train_agent.run(cfg("train_agent", f"seed={seed}"))
    ev = cfg("evaluate", "evaluate.family=chae", "evaluate.chae.ensemble=2")
    agents = [AgentId.of(cfg("train_agent", f"seed={s}")) for s in (0, 1)]
    members = [chae.load_policy(ev, a) for a in agents]
    (ensemble,) = chae.ensembles(agents, members, 2)
    assert (ensemble.name, ensemble.policy_seed) == ("agent_chae_dqn_chae_ensemble2", 0)
    # metres and m/s: states at the scale of real ones, where the smoke-trained members disagree
    obs = (5.0 * np.random.default_rng(0).normal(size=(300, members[0].see.dim))).astype(np.float32)
    q0, q1 = (m.agent.q_values(obs) for m in members)
    np.testing.assert_allclose(ensemble.agent.q_values(obs), (q0 + q1) / 2, rtol=1e-6)
    chosen = [ensemble.agent.act(o) for o in obs]
    assert chosen == ((q0 + q1) / 2).argmax(1).tolist()
    assert chosen != q0.argmax(1).tolist() or chosen != q1.argmax(1).tolist()  # not simply one member
    assert chae.ensembles(agents, members, 3) == []  # seed 2 missing: no partial ensemble
    # the Euro NCAP bank drives the agents as the family's evaluation does: alone and in ensembles, or ensembles only
    for singles, expected in (("true", [("agent_chae_dqn_chae", 0), ("agent_chae_dqn_chae", 1)]), ("false", [])):
        ncap_cfg = cfg("ncap", "evaluate.chae.ensemble=2", f"evaluate.chae.singles={singles}")
        learned = [(p.name, seed) for p, seed, *_ in chae.ncap_policies(ncap_cfg) if hasattr(p, "agent")]
        assert learned == [*expected, ("agent_chae_dqn_chae_ensemble2", 0)]

    summary = chae.evaluate(ev)
    rows = list(csv.DictReader(open(tmp_path / "runs/e/eval_chae/results.csv")))
    per_policy = {p: sum(r["policy"] == p for r in rows) for p in {r["policy"] for r in rows}}
    assert per_policy["agent_chae_dqn_chae_ensemble2"] == per_policy["braking"] == 12  # 3 TTCs + Scenario 2, 3 each
    assert per_policy["agent_chae_dqn_chae"] == 24  # the two seeds alone, as before
    assert set(summary["policies"]) >= set(chae.SCRIPTED)
    first = tmp_path / "first"
    shutil.copytree(tmp_path / "runs/e/eval_chae", first)
    # the ensembles alone, with one scripted policy (evaluate.chae.policies): the same trials give the same rows
    alone_args = (
        "evaluate",
        "evaluate.family=chae",
        "evaluate.chae.ensemble=2",
        "evaluate.chae.singles=false",
        "evaluate.chae.policies=[braking]",
    )
    alone = chae.evaluate(cfg(*alone_args))
    assert set(alone["policies"]) == {"braking", "agent_chae_dqn_chae_ensemble2"}
    for name in alone["policies"]:
        assert alone["policies"][name] == summary["policies"][name]
    # experiments.chae_tables: the rows read back give the evaluation's tables; a run given twice is refused
    from experiments import chae_tables

    chae_tables.main([str(first / "results.csv"), "--out", str(tmp_path / "joined.md")])
    assert (tmp_path / "joined.md").read_text() == (first / "tables.md").read_text()
    with pytest.raises(SystemExit, match="braking seed 0 is in both"):
        chae_tables.join([first / "results.csv", tmp_path / "runs/e/eval_chae/results.csv"])
    with pytest.raises(StageError, match="evaluate.chae.policies.*closing_braking"):
        validate(cfg("evaluate", "evaluate.family=chae", "evaluate.chae.policies=[braking,aeb3m]"))
    with pytest.raises(StageError, match="evaluate.chae.ensemble=1"):
        validate(cfg("evaluate", "evaluate.family=chae", "evaluate.chae.ensemble=1"))
    with pytest.raises(StageError, match="evaluate.chae.singles"):
        validate(cfg("evaluate", "evaluate.family=chae", "evaluate.chae.ensemble=0", "evaluate.chae.singles=false"))


def test_the_configs_scripted_names_are_the_ones_evaluation_builds():
    from worldmodel.families.chae import system as chae
    from worldmodel.families.chae.config import SCRIPTED_POLICIES

    assert tuple(chae.SCRIPTED) == SCRIPTED_POLICIES


def test_the_evaluation_steps_at_the_papers_0_1_s_without_the_agent_preset():
    """`evaluate evaluate.family=chae` does not load conf/agent/dqn_chae.yaml (which sets env.step_s=0.1); the
    family's env must still step every 0.1 s, as its agents were trained and chosen."""
    from worldmodel.config import compose
    from worldmodel.families.chae import system as chae

    cfg = compose("evaluate", ["experiment=x", "evaluate.family=chae"])
    assert cfg.env.step_s != 0.1  # the default street's 1/15 s: the case this guards
    for end_on_bump in (True, False):
        env = chae.family_env(cfg, camera=False, end_on_bump=end_on_bump)
        assert env.step_s == 0.1
        env.close()


def test_the_bars_are_judged_run_by_run():
    """bars_per_run: each (policy, seed) on its own, its worst TTC from 1.5 s (bumps <= 1 %) and its Scenario-2
    stops (<= 5 %); TTCs below 1.5 s do not count."""
    from worldmodel.families.chae.system import bars_per_run

    def trials(policy, seed, ttc, bumps, n=100):
        return [
            {"policy": policy, "policy_seed": seed, "scenario": 1, "ttc": ttc, "bump": int(i < bumps)} for i in range(n)
        ]

    def scenario2(policy, seed, stops, n=100):
        return [
            {"policy": policy, "policy_seed": seed, "scenario": 2, "end": "stop" if i < stops else "pass"}
            for i in range(n)
        ]

    rows = []
    for seed, (early, at15, at17, stops) in enumerate([(90, 1, 0, 5), (90, 0, 2, 0), (0, 0, 0, 6)]):
        rows += trials("dqn", seed, 1.3, early) + trials("dqn", seed, 1.5, at15) + trials("dqn", seed, 1.7, at17)
        rows += scenario2("dqn", seed, stops)
    got = {
        (r["seed"]): (r["max_bump"], r["at_ttc"], r["stops"], r["inside"]) for r in bars_per_run(rows, [1.3, 1.5, 1.7])
    }
    assert got == {0: (1.0, 1.5, 5.0, True), 1: (2.0, 1.7, 0.0, False), 2: (0.0, 1.5, 6.0, False)}
    assert bars_per_run(rows, [1.3]) == []
    # each judged rate carries its Wilson 95 % interval: 2 in 100 is [0.55, 7.0] %, 0 in 100 is [0, 3.7] %
    second = bars_per_run(rows, [1.3, 1.5, 1.7])[1]
    assert second["max_bump_ci95"] == pytest.approx([0.55, 7.0], abs=0.01)
    assert second["stops_ci95"] == pytest.approx([0.0, 3.70], abs=0.01)


def test_the_training_ttc_range_reaches_the_episodes_and_the_preset_widens_the_papers(tmp_path):
    """agent.chae.ttc_range: the schema's default draws the paper's episodes exactly; the preset's lower bound of
    1.3 s rescales only the TTC of the same draws, and it reaches the training loop (the trained network differs).
    An empty or inverted range is refused, naming the key."""
    import torch

    from worldmodel import artifacts, train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.common import StageError
    from worldmodel.config import AgentConfig, validate
    from worldmodel.families.chae.system import episode_scenario

    def cfg(root, *extra):
        return smoke_dqn_chae(root, "agent.chae.select.every=0", *extra)

    for episode in range(50):
        (paper, _), (wide, _) = episode_scenario(3, episode), episode_scenario(3, episode, [1.3, 4.0])
        assert episode_scenario(3, episode, [1.5, 4.0]) == episode_scenario(3, episode)
        assert (wide.v_init, wide.v_ped, wide.crosses, wide.seed) == (
            paper.v_init,
            paper.v_ped,
            paper.crosses,
            paper.seed,
        )
        assert wide.ttc == pytest.approx(1.3 + (paper.ttc - 1.5) * 2.7 / 2.5)
    assert min(episode_scenario(3, e, [1.3, 4.0])[0].ttc for e in range(50)) < 1.5

    assert AgentConfig().chae.ttc_range == [1.5, 4.0]  # the schema's
    default, wide = cfg(tmp_path / "paper", "agent.chae.ttc_range=[1.5,4.0]"), cfg(tmp_path / "wide")
    assert list(wide.agent.chae.ttc_range) == [1.3, 4.0]  # the preset's
    assert artifacts.provenance(wide, "agent") != artifacts.provenance(default, "agent")
    for bad in ("[2.0,1.5]", "[1.5]", "[0.0,4.0]", "[1.5,6.0]"):
        with pytest.raises(StageError, match="agent.chae.ttc_range"):
            validate(cfg(tmp_path / "bad", f"agent.chae.ttc_range={bad}"))
    train_agent.run(default)
    train_agent.run(wide)
    nets = [
        torch.load(AgentId.of(c).dir(c) / "last.pt", weights_only=False)["agent"]["q_network"] for c in (default, wide)
    ]
    assert any(not torch.equal(w, nets[1][name]) for name, w in nets[0].items())


def test_the_state_noise_is_a_setting_that_the_checkpoint_carries_into_evaluation(tmp_path):
    """agent.chae.noise_m: the preset's 0.05 m and any other value are different runs; a run trained without noise
    records it, and the policy evaluation loads from that checkpoint sees the exact relative position (the same
    reading whatever the observer's seed), where the default's readings differ by seed. A negative noise is
    refused."""
    import torch

    from envs.chae import ChaeSpec
    from worldmodel import artifacts, train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.common import StageError
    from worldmodel.config import validate
    from worldmodel.families.chae.system import family_env, load_policy, observer

    def cfg(root, *extra):
        return smoke_dqn_chae(root, "agent.chae.select.every=0", *extra)

    default, exact = cfg(tmp_path / "paper"), cfg(tmp_path / "exact", "agent.chae.noise_m=0")
    assert default.agent.chae.noise_m == 0.05  # the preset's
    assert artifacts.provenance(cfg(tmp_path / "paper", "agent.chae.noise_m=0.05"), "agent") == (
        artifacts.provenance(default, "agent")
    )
    for other in (exact, cfg(tmp_path / "first_twenty", "agent.chae.noise_m=0.1")):
        assert artifacts.provenance(other, "agent") != artifacts.provenance(default, "agent")
    with pytest.raises(StageError, match="agent.chae.noise_m"):
        validate(cfg(tmp_path / "bad", "agent.chae.noise_m=-0.1"))
    train_agent.run(exact)
    agent_id = AgentId.of(exact)
    assert torch.load(agent_id.dir(exact) / "last.pt", weights_only=False)["noise_m"] == 0.0

    policy = load_policy(exact, agent_id)
    assert policy.see.view.noise_m == 0.0  # the checkpoint's record, not the evaluating config's default
    spec = ChaeSpec(seed=0, ttc=2.0, v_init=8.0, v_ped=3.0)
    env = family_env(exact, camera=False)

    def readings(see):
        out = []
        for seed in (1, 2):
            obs, _ = env.reset(options={"scenario": spec})
            see.reset(seed)
            out.append(see(env, obs))
        return out

    exact_readings, noisy_readings = readings(policy.see), readings(observer(default, "pedestrian_history"))
    env.close()
    np.testing.assert_array_equal(exact_readings[0], exact_readings[1])
    assert not np.array_equal(noisy_readings[0], noisy_readings[1])
