"""``experiments/critic_vs_exact.py``: how a learned critic ranks the chooser's candidates against their exact costs.
The figures by hand (a constant critic orders half the pairs, a perfect one all, a reversed one none), the shifts
that stand for the chooser's candidates drive exactly as they do, and the script on a smoke DDPG and the smoke
validation bank's labels."""

from __future__ import annotations

import csv
import shutil

import numpy as np
import pytest

from envs.chooser import chooser_candidates
from experiments import critic_vs_exact as cve

COSTS = np.array([[0.3, 0.1, 0.2, 0.0], [0.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.1, 0.2]])


def test_the_figures_by_hand():
    s = cve.per_state(np.ones_like(COSTS), COSTS)  # a constant critic
    assert s["pairs"].tolist() == [6, 0, 5]  # the second state's costs are all equal: no pair, no Spearman
    assert s["agree"].tolist() == [3.0, 0.0, 2.5]
    assert s["spearman"][0] == 0.0 and np.isnan(s["spearman"][1]) and s["spearman"][2] == 0.0
    assert s["pick"].tolist() == [0, 0, 0] and s["pick_lowest"].tolist() == s["brake_lowest"].tolist()
    assert s["brake_lowest"].tolist() == [False, True, False]
    f = cve.summarize(np.ones_like(COSTS), COSTS, np.array([0, 1, 2]), boot=200)
    assert f["pairwise"] == 0.5 and f["spearman"] == 0.0 and f["ranked_states"] == 2
    assert f["pick_brakes"] == 1.0 and f["pick_minus_brake"] == 0.0

    perfect = cve.summarize(COSTS, COSTS, np.array([0, 0, 1]), boot=200)
    assert perfect["pairwise"] == 1.0 and perfect["spearman"] == pytest.approx(1.0)
    assert perfect["pick_lowest"] == 1.0
    assert perfect["pick_minus_brake"] == pytest.approx(np.mean([0.0 - 0.3, 0.0, 0.1 - 0.5]))
    assert perfect["pairwise_ci"] == (1.0, 1.0)
    reverse = cve.summarize(-COSTS, COSTS, np.array([0, 0, 1]), boot=200)
    assert reverse["pairwise"] == 0.0 and reverse["spearman"] == pytest.approx(-1.0)
    # the third state's tie (two candidates at 0.5) ranked by hand: costs' ranks (3.5, 3.5, 1, 2) against (1, 2, 3, 4)
    tied = cve.per_state(np.array([[1.0, 2.0, 3.0, 4.0]]), COSTS[2:])
    assert tied["spearman"][0] == pytest.approx(np.corrcoef([3.5, 3.5, 1, 2], [1, 2, 3, 4])[0, 1])
    assert cve.matters(COSTS).tolist() == [True, False, True]


def test_the_shifts_drive_the_candidates_and_a_held_swerve_has_none():
    step_s = 1 / 15
    candidates = chooser_candidates(lane_change_s=(0.3,), swerve=False, step_s=step_s)
    u = cve.shift_inputs(candidates, (0.15, 0.6), step_s)
    assert u[0].tolist() == [0.0, 0.0, 0.0] and (u[1:, 1] == 0).all()  # braking; full braking pedal throughout
    assert sorted(u[1:, 0].tolist()) == pytest.approx([-1.0, -0.3, 0.3, 1.0])
    with pytest.raises(ValueError, match="no shift drives"):
        cve.shift_inputs(chooser_candidates(swerve=True, step_s=step_s), (0.15, 0.6), step_s)
    assert "distinct" in cve.first_action_note(candidates)
    assert "share" in cve.first_action_note(chooser_candidates(swerve=True, step_s=step_s))


def test_a_sealed_draw_or_the_test_bank_is_refused(capsys):
    with pytest.raises(SystemExit) as stop:
        cve.main(["--validation-seed", "56171"])
    assert stop.value.code == 2 and "is a sealed test seed: choose a validation draw" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        cve.main(["evaluate.bank=test"])
    assert stop.value.code == 2 and "sealed" in capsys.readouterr().err


def test_on_a_smoke_ddpg(smoke_builds, tmp_path, capsys):
    from worldmodel import chooser, loading, train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.config import compose

    shutil.copytree(smoke_builds("rnn"), tmp_path, dirs_exist_ok=True)
    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke"]
    base += ["threads=1", f"paths.ledger={tmp_path}/ledger.csv"]
    train_agent.run(compose("train_agent", [*base, "reward=r2"]))
    assert cve.main([*base, "agent.chooser.num_workers=1", "--boot", "100"]) == 0
    out = tmp_path / "runs" / "t" / "critic_vs_exact"
    assert "| agent_r2/seed0 | DDPG -Q | 0-" in (out / "critic_vs_exact.md").read_text()
    with (out / "critic_vs_exact.csv").open() as f:
        rows = list(csv.DictReader(f))
    cfg = compose("train_agent", [*base, "reward=r2", "agent=chooser", "agent.chooser.num_workers=1"])
    val = chooser.labels(cfg, "validation")
    assert len(rows) == len(val["t"]) and {r["agent"] for r in rows} == {"agent_r2/seed0"}
    for r in rows:
        if r["spearman"]:
            assert -1.0 <= float(r["spearman"]) <= 1.0
        assert 0 <= float(r["agree"]) <= int(r["pairs"])

    # the critic's own Q on the labelled states, and a critic made constant orders exactly half of the pairs
    state = loading.load_agent_state(cfg, AgentId("r2", 0), "last")
    candidates = chooser.cfg_chooser(cfg).candidates(cfg.env.step_s)
    encoder = loading.load_world_model(cfg, **loading.agent_input(state, cfg.vae.latent_dim))
    x = chooser.encode_labels(encoder, val)
    scores = cve.ddpg_scores(state, x, val["speed"], candidates)
    f = cve.summarize(scores, val["costs"], val["episode"], boot=100)
    assert 0.0 <= f["pairwise"] <= 1.0 and -1.0 <= f["spearman"] <= 1.0
    assert [float(r["score_0"]) for r in rows] == pytest.approx(scores[:, 0].tolist(), rel=1e-5)
    last = max(k for k in state["agent"]["critic"] if k.endswith(".weight"))
    state["agent"]["critic"][last].zero_()
    flat = cve.ddpg_scores(state, x, val["speed"], candidates)
    assert np.ptp(flat, axis=1).max() == 0.0
    assert cve.summarize(flat, val["costs"], val["episode"], boot=0)["pairwise"] == 0.5


def test_kims_critic_on_a_smoke_lidar_ddpg(tmp_path):
    """experiments/kim_critic_vs_exact.py: the labels on a validation draw of family kim, and a smoke LIDAR DDPG's
    critic scoring each candidate's first control as Kim's action; the score is -Q of the agent the evaluation
    loads, and Kim's action asks the speed controller for the candidate's own control."""
    import torch

    from envs.kim import kim_action
    from experiments import kim_critic_vs_exact as kim_cve
    from worldmodel import train_agent
    from worldmodel.artifacts import AgentId
    from worldmodel.config import compose
    from worldmodel.families.kim import chooser as kim_chooser
    from worldmodel.families.kim.trainer import load_policy

    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke"]
    base += ["threads=1", f"paths.ledger={tmp_path}/ledger.csv"]
    train_agent.run(compose("train_agent", [*base, "agent=ddpg_kim"]))
    assert kim_cve.main([*base, "--trials", "1", "--boot", "50"]) == 0
    out = tmp_path / "runs" / "t" / "critic_vs_exact"
    assert "| agent_kim_unaware_ddpg_kim/seed0 | DDPG -Q | 0-" in (out / "kim_critic_vs_exact_draw2020.md").read_text()
    with (out / "kim_critic_vs_exact_draw2020.csv").open() as f:
        rows = list(csv.DictReader(f))

    cfg = compose("train_agent", [*base, "agent=kim_chooser"])
    val = kim_cve.labels(cfg, 2020, 1)  # read back, not made again
    assert len(rows) == len(val["t"]) == len(val["speed"]) and val["costs"].shape[1] == 39
    candidates = kim_chooser.candidates(cfg.env.step_s)
    for v in (0.5, 8.0, 13.9):
        for m in candidates:
            steer, pedal = m.action(0)
            got = kim_action(kim_cve.kim_action_for(m.action(0), v), v)
            reachable = got[1] == pytest.approx(pedal, abs=1e-6) or (pedal < 0 and v < 2.0)  # full braking when slow
            assert got[0] == pytest.approx(steer) and reachable
    agent = AgentId("kim_unaware", 0, "ddpg_kim")
    policy, _ = load_policy(compose("train_agent", [*base, "agent=ddpg_kim"]), agent)
    i, k = 1, 5
    action = torch.from_numpy(kim_cve.kim_action_for(candidates[k].action(0), float(val["speed"][i]))[None])
    with torch.inference_mode():
        q = policy.agent.critic(torch.from_numpy(val["view"][i : i + 1]), action)
    assert float(rows[i][f"score_{k}"]) == pytest.approx(-float(q), rel=1e-4)
