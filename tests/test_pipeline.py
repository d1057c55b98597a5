"""End to end: every stage at scale=smoke from an empty experiment, then the checks that need trained parts."""

from __future__ import annotations

import csv
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from envs import StraightLineBraking
from worldmodel import (
    artifacts,
    banks,
    evaluate,
    loading,
    ncap,
    pipeline,
    policies,
    train_agent,
    train_vae,
)
from worldmodel.common import StageError, make_env
from worldmodel.config import compose, validate
from worldmodel.families import common as peers_common
from worldmodel.families.porav import evaluation as porav_eval
from worldmodel.report import published, read_results_csv, recheck

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow  # every stage at scale=smoke, end to end

OUTPUTS = [
    "data/t/rollouts/manifest.json",
    "data/t/latents.h5",
    "runs/t/vae/best.pt",
    "runs/t/vae/last.pt",
    "runs/t/vae/metrics.json",
    "runs/t/rnn/best.pt",
    "runs/t/rnn/last.pt",
    "runs/t/rnn/metrics.json",
    "runs/t/agent_r1/seed0/last.pt",
    "runs/t/agent_r1/seed0/metrics.json",
    "runs/t/agent_r2/seed0/last.pt",
    "runs/t/agent_r2/seed0/metrics.json",
    "runs/t/agent_r2_chooser/seed0/last.pt",
    "runs/t/agent_r2_chooser/seed0/metrics.json",
    "runs/t/agent_r2_counterfactual/seed0/last.pt",
    "runs/t/agent_r2_counterfactual/seed0/metrics.json",
    "runs/t/eval/results.csv",
    "runs/t/eval/summary.json",
    "runs/t/eval/tables.md",
    "runs/t/eval/heatmaps.png",
    "runs/t/eval_test/summary.json",
    "runs/t/pipeline.json",
]
BANKS = "banks=[validation,test]"  # the validation bank, then the sealed test bank once


def smoke_cfg_overrides(root) -> list[str]:
    return [
        f"paths.data_root={root}/data",
        f"paths.runs_root={root}/runs",
        f"paths.ledger={root}/ledger.csv",
        "experiment=t",
        "scale=smoke",
        "threads=1",
    ]


def smoke_cfg(root, stage="pipeline", *overrides):
    return compose(stage, [*smoke_cfg_overrides(root), *overrides])


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    pipeline.run(smoke_cfg(root, "pipeline", BANKS))
    return root


def test_pipeline_produces_every_output(experiment):
    for rel in OUTPUTS:
        assert (experiment / rel).exists(), rel
    rows = read_results_csv(experiment / "runs/t/eval/results.csv")
    policies = {"braking", "agent_r1", "agent_r2", "agent_r2_chooser", "agent_r2_counterfactual", "oracle"}
    assert {r["policy"] for r in rows} == policies
    per_policy = len(porav_eval.bank(smoke_cfg(experiment, "evaluate")))
    assert len(rows) == len(policies) * per_policy
    summary = json.loads((experiment / "runs/t/eval/summary.json").read_text())
    assert set(summary["policies"]) == policies
    assert set(summary["achievable_share"]["policies"]) == policies - {"braking"}
    timings = json.loads((experiment / "runs/t/pipeline.json").read_text())
    assert set(timings) == {
        *("collect", "vae", "rnn", "agent_r1", "agent_r2", "agent_r2_chooser", "agent_r2_counterfactual"),
        *("eval", "eval_test"),
    }
    assert all(t["wall_s"] > 0 and t["peak_rss_mb"] > 0 for t in timings.values())
    assert not any(t["untimed_part"] for t in timings.values())  # one uninterrupted run: every second recorded
    tables = (experiment / "runs/t/eval/tables.md").read_text()
    assert "Brake&Steer, reward 1" in tables and "Table III" in tables and "Table IV" in tables


def test_second_run_skips_finished_stages(experiment, caplog):
    stamps = {rel: (experiment / rel).stat().st_mtime_ns for rel in OUTPUTS}
    with caplog.at_level(logging.INFO, logger="worldmodel.pipeline"):
        pipeline.run(smoke_cfg(experiment, "pipeline", BANKS))
    assert caplog.text.count("skipped") == 9 and "running" not in caplog.text
    assert stamps == {rel: (experiment / rel).stat().st_mtime_ns for rel in OUTPUTS}
    # the test bank judged these agents once: one ledger row, every agent with the hashes of its models
    (row,) = banks.read_ledger(experiment / "ledger.csv")
    assert row["family"] == "porav" and row["experiment"] == "t"
    for key in ("agent_r1/seed0", "agent_r2/seed0", "agent_r2_chooser/seed0", "agent_r2_counterfactual/seed0"):
        assert f"{key} (vae=" in row["policies"], key
    assert "agent_r2_chooser: share " in row["headline"]


def test_the_plan_says_what_a_run_would_do_and_runs_nothing(experiment, tmp_path):
    """plan=true on a finished experiment: every step complete with its recorded time; a new seed's time to go is
    that of its finished seeds. With the LSTM unfinished, the LSTM resumes and the steps that read it are complete
    now but checked again after it; nothing is written."""
    empty = pipeline.run(smoke_cfg(tmp_path / "empty", "pipeline", BANKS, "plan=true"))["plan"]
    assert {r["state"] for r in empty} == {"fresh"}  # the collection too: nothing of it to resume
    done = pipeline.run(smoke_cfg(experiment, "pipeline", BANKS, "plan=true"))["plan"]
    timings = json.loads((experiment / "runs/t/pipeline.json").read_text())
    assert [(r["step"], r["state"], r["wall_s"]) for r in done] == [
        (name, "complete", timings[name]["wall_s"]) for name in timings
    ]
    # a new seed: its time to go is its finished seeds' (the median of one)
    seeds = {
        r["step"]: r for r in pipeline.run(smoke_cfg(experiment, "pipeline", BANKS, "seeds=[0,1]", "plan=true"))["plan"]
    }
    new_seed = seeds["agent_r1/seed1"]
    assert (new_seed["state"], new_seed["estimate_s"]) == ("fresh", timings["agent_r1"]["wall_s"])
    assert seeds["agent_r1"]["estimate_s"] is None  # complete: nothing to go
    root = tmp_path / "copy"
    shutil.copytree(experiment, root)
    (root / "runs/t/rnn/metrics.json").unlink()  # as if the LSTM had been stopped before it finished
    before = sorted((p, p.stat().st_mtime_ns) for p in root.rglob("*"))
    rows = {r["step"]: r for r in pipeline.run(smoke_cfg(root, "pipeline", BANKS, "plan=true"))["plan"]}
    assert {name: r["state"] for name, r in rows.items()} == {
        "collect": "complete", "vae": "complete", "rnn": "resume", "agent_r1": "after", "agent_r2": "after",
        "agent_r2_chooser": "after", "agent_r2_counterfactual": "after", "eval": "after", "eval_test": "after",
    }  # fmt: skip
    assert rows["agent_r1"]["reasons"] == ["checked again once rnn ran"]
    assert rows["eval"]["reasons"] == [
        "checked again once agent_r1, agent_r2_chooser, agent_r2_counterfactual, agent_r2 ran"
    ]  # their order
    assert sorted((p, p.stat().st_mtime_ns) for p in root.rglob("*")) == before


def test_the_pipeline_trains_every_seed_of_seeds(tmp_path):
    names = [s.name for s in pipeline.steps(smoke_cfg(tmp_path, "pipeline", "agents=[ddpg]", "seeds=[0,2]", BANKS))]
    assert names == [
        "collect", "vae", "rnn", "agent_r1", "agent_r1/seed2", "agent_r2", "agent_r2/seed2", "eval", "eval_test"
    ]  # fmt: skip


def test_a_run_of_peers_alone_leaves_the_paper_family_and_its_test_bank_alone(experiment):
    """agents=[] on an experiment whose paper agents are trained and judged: none of them is checked, retrained or
    evaluated again. Peers are named by family or by preset, train every seed of seeds (Chae: the members of one
    ensemble per seed), and each family is evaluated on each bank right after its own agents."""
    cfg = smoke_cfg(experiment, "pipeline", "agents=[]", "peers=[merola,ddpg_kim_fd,chae]", "seeds=[0,1]", BANKS)
    names = [s.name for s in pipeline.steps(cfg)]
    chae = ["agent_chae_dqn_chae", *(f"agent_chae_dqn_chae/seed{s}" for s in range(1, 6))]
    assert names == [
        "collect", "vae", "rnn",
        "agent_merola_ddqn_merola", "agent_merola_ddqn_merola/seed1", "eval_merola", "eval_merola_test",
        "agent_kim_unaware_ddpg_kim_fd", "agent_kim_unaware_ddpg_kim_fd/seed1", "eval_kim", "eval_kim_test",
        *chae, "eval_chae", "eval_chae_test",
    ]  # fmt: skip
    with pytest.raises(StageError, match="peers"):
        validate(smoke_cfg(experiment, "pipeline", "peers=[ddpg]"))  # the paper's own preset is no peer


def test_the_pipeline_trains_a_preset_built_on_another_as_train_agent_would(tmp_path):
    """chooser_tele extends chooser from a global package (``/agent/chooser@agent``): the pipeline's agent section
    and env change are the ones `train_agent agent=chooser_tele` composes."""
    from omegaconf import OmegaConf

    from worldmodel.config import agent_preset

    cfg = smoke_cfg(tmp_path, "pipeline", "agents=[chooser_tele]")
    composed = smoke_cfg(tmp_path, "train_agent", "agent=chooser_tele")
    assert OmegaConf.to_container(agent_preset(cfg, "chooser_tele")) == OmegaConf.to_container(composed.agent)
    (step,) = [s for s in pipeline.steps(cfg) if s.kind == "agent"]
    assert step.name == "agent_r2_chooser_tele" and step.changes["env"] == {"tele_fov_deg": 30.0}


def test_agent_resume_continues_step_count(experiment, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(experiment, root)
    shutil.rmtree(root / "runs/t/agent_r1")
    train_agent.run(smoke_cfg(root, "train_agent", "reward=r1", "agent.total_steps=150"))
    first = torch.load(root / "runs/t/agent_r1/seed0/last.pt", weights_only=False)
    assert first["step"] == 150
    with pytest.raises(StageError, match="resume=true"):
        train_agent.run(smoke_cfg(root, "train_agent", "reward=r1", "agent.total_steps=300"))
    train_agent.run(smoke_cfg(root, "train_agent", "reward=r1", "agent.total_steps=300", "resume=true"))
    second = torch.load(root / "runs/t/agent_r1/seed0/last.pt", weights_only=False)
    assert second["step"] == 300 and len(second["buffer"]["obs"]) == 300
    assert np.array_equal(second["buffer"]["obs"][:150], first["buffer"]["obs"][:150])


def test_missing_world_model_names_the_command(tmp_path):
    with pytest.raises(StageError, match="worldmodel.train_vae experiment=t"):
        train_agent.run(smoke_cfg(tmp_path, "train_agent", "reward=r1"))
    with pytest.raises(StageError, match="reward.name"):
        train_agent.run(smoke_cfg(tmp_path, "train_agent", "reward.name=r3"))


def test_braking_evaluation_is_bit_reproducible(tmp_path):
    cfg = smoke_cfg(tmp_path, "evaluate")
    entries = porav_eval.bank(cfg)
    runs = []
    for _ in range(2):
        env = make_env(cfg, camera=False)
        runs.append(porav_eval.run_policy(env, StraightLineBraking(), entries, desc=False))
        env.close()
    assert repr(runs[0]) == repr(runs[1])
    # every row says how its episode ended, and the speed then
    assert {r["end"] for r in runs[0]} <= {"crash", "left_scene", "horizon"}
    assert all(0.0 <= r["final_speed"] <= r["speed"] for r in runs[0])
    # ...and the camera does not change any outcome.
    env = make_env(cfg, camera=True)
    assert repr(porav_eval.run_policy(env, StraightLineBraking(), entries, desc=False)) == repr(runs[0])


def test_parallel_evaluation_equals_one_process(experiment):
    cfg = smoke_cfg(experiment, "evaluate")
    entries = porav_eval.bank(cfg)[:4]
    # the planner (scripted, re-simulating in the workers), an agent and the chooser (torch in the workers), one
    # pool serving all three in turn: how scenarios are split among workers must not matter
    names = ["oracle", "agent_r2/seed0", "agent_r2_chooser/seed0"]
    one = porav_eval.evaluate_policies(cfg, names, entries, workers=1)
    two = porav_eval.evaluate_policies(cfg, names, entries, workers=2)
    assert list(two) == names and repr(one) == repr(two)


def test_evaluation_rows_name_the_models_that_produced_them(experiment):
    cfg = smoke_cfg(experiment, "evaluate")
    rows = read_results_csv(experiment / "runs/t/eval/results.csv")
    vae, rnn = artifacts.short(artifacts.vae_id(cfg)), artifacts.short(artifacts.rnn_id(cfg))
    for row in rows:
        if row["policy"].startswith("agent_"):
            agent = artifacts.AgentId.parse(f"{row['policy']}/seed{row['policy_seed']}")
            assert (row["vae_sha"], row["rnn_sha"]) == (vae, rnn) and len(vae) == 12
            assert row["actor_sha"] == artifacts.short(artifacts.actor_id(cfg, agent))
        else:
            assert row["vae_sha"] == row["rnn_sha"] == row["actor_sha"] == ""
    assert len({r["actor_sha"] for r in rows if r["policy"].startswith("agent_")}) == 4


@pytest.fixture(scope="module")
def new_vae(experiment, tmp_path_factory):
    """A copy of the experiment whose VAE was retrained (another KL weight) by its stage command."""
    root = tmp_path_factory.mktemp("new_vae")
    shutil.copytree(experiment, root, dirs_exist_ok=True)
    shutil.rmtree(root / "runs/t/vae")
    train_vae.run(smoke_cfg(root, "train_vae", "vae.kl_weight=0.5"))
    return root


def test_agent_built_on_another_vae_refuses_to_load(new_vae):
    cfg = smoke_cfg(new_vae, "evaluate", "vae.kl_weight=0.5")
    agent = artifacts.AgentId("r1", 0)
    with pytest.raises(StageError, match=r"agent_r1/seed0/last.pt is stale: it was built on vae") as err:
        loading.load_actor(cfg, agent)
    assert str(new_vae / "runs/t/vae/best.pt") in str(err.value)
    assert "python -m worldmodel.train_agent experiment=t reward=r1 seed=0" in str(err.value)
    actor, _ = loading.load_actor(smoke_cfg(new_vae, "evaluate", "vae.kl_weight=0.5", "allow_stale=true"), agent)
    with pytest.raises(StageError, match="stale"):  # evaluation stops before any scenario runs
        evaluate.run(cfg)


def test_an_agent_on_the_frozen_vaes_frames_is_stale_on_another_vae(experiment, new_vae, tmp_path):
    """ddqn_merola sees the frozen VAE's means of its frames (obs=frames_vae): it records the VAE as its input, a new
    VAE makes it stale for the pipeline and refuses its checkpoint, and a run recorded before the VAE was an input
    (no input at all) is taken as built on the current VAE."""
    from worldmodel.families.merola import system as merola

    root = tmp_path / "copy"
    shutil.copytree(experiment, root)
    preset = ("agent=ddqn_merola", "agent.total_steps=100")
    train_agent.run(smoke_cfg(root, "train_agent", *preset))
    cfg = smoke_cfg(root, "train_agent", *preset)
    agent = artifacts.AgentId.of(cfg)
    run_dir = agent.dir(cfg)
    assert artifacts.read_provenance(run_dir)["inputs"] == {"vae": artifacts.vae_id(cfg)}

    shutil.rmtree(root / "runs/t/vae")
    shutil.copytree(new_vae / "runs/t/vae", root / "runs/t/vae")  # another VAE, as a rebuild would leave it
    current = artifacts.provenance(cfg, "agent", agent)
    assert [r.split(" ")[0] for r in artifacts.differences(artifacts.read_provenance(run_dir), current)] == ["vae"]
    with pytest.raises(StageError, match=r"agent_merola_ddqn_merola/seed0/last.pt is stale: it was built on vae"):
        merola.load_policy(smoke_cfg(root, "evaluate", "evaluate.family=merola"), agent)

    # recorded before the VAE was an input: no input at all, in the record and in the checkpoint (and, as then,
    # no digests of the run's checkpoints)
    record = artifacts.read_provenance(run_dir)
    record.pop("outputs")
    artifacts.write_provenance(run_dir, {**record, "inputs": {}})
    state = torch.load(run_dir / "last.pt", weights_only=False)
    torch.save({**state, "provenance": {**state["provenance"], "inputs": {}}}, run_dir / "last.pt")
    assert artifacts.differences(artifacts.read_provenance(run_dir), current) == []
    merola.load_policy(smoke_cfg(root, "evaluate", "evaluate.family=merola"), agent)


def test_pipeline_rebuilds_what_a_new_vae_made_stale(new_vae, caplog):
    # shorter agents and no planner in the evaluation keep the rebuild quick; the new VAE alone makes them stale
    cfg = smoke_cfg(new_vae, "pipeline", "vae.kl_weight=0.5", "agent.total_steps=150", "evaluate.policies=[braking]")
    kept = {rel: (new_vae / rel).stat().st_mtime_ns for rel in ("data/t/rollouts/manifest.json", "runs/t/vae/best.pt")}
    with caplog.at_level(logging.INFO, logger="worldmodel.pipeline"):
        pipeline.run(cfg)
    log = caplog.text
    assert "collect: complete" in log and "vae: complete" in log
    for name in ("rnn", "agent_r1", "agent_r2", "agent_r2_chooser", "agent_r2_counterfactual", "eval"):
        assert f"{name}: stale" in log, log
    assert kept == {rel: (new_vae / rel).stat().st_mtime_ns for rel in kept}
    vae = artifacts.vae_id(cfg)
    from worldmodel.latents import Latents

    lat = Latents(new_vae / "data/t/latents.h5")
    assert lat.f.attrs["vae_sha256"] == vae
    lat.close()
    assert artifacts.read_provenance(new_vae / "runs/t/rnn")["inputs"]["vae"] == vae
    for reward in ("r1", "r2"):
        assert artifacts.read_provenance(new_vae / f"runs/t/agent_{reward}/seed0")["inputs"]["vae"] == vae
    rows = read_results_csv(new_vae / "runs/t/eval/results.csv")
    assert {r["vae_sha"] for r in rows if r["policy"].startswith("agent_")} == {artifacts.short(vae)}
    stale = sorted(p.name.rsplit("-", 2)[0] for p in (new_vae / "runs/t/stale").iterdir())
    assert stale == [
        "agent_r1-seed0", "agent_r2-seed0", "agent_r2_chooser-seed0", "agent_r2_counterfactual-seed0", "eval", "rnn"
    ]  # fmt: skip
    # Now everything is up to date again: a rerun does nothing.
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="worldmodel.pipeline"):
        pipeline.run(cfg)
    assert caplog.text.count("skipped") == 8


def test_each_agent_is_evaluated_with_its_own_input_and_action_map(experiment, tmp_path):
    """An agent trained with speed in its input and the braking anchor is evaluated that way, whatever the
    evaluation's own agent.* settings say."""
    root = tmp_path / "copy"
    shutil.copytree(experiment, root)
    shutil.rmtree(root / "runs/t/agent_r1")
    options = ("agent.use_speed=true", "agent.anchor=brake", "agent.steer=grip")
    train_agent.run(smoke_cfg(root, "train_agent", "reward=r1", "agent.total_steps=150", *options))
    cfg = smoke_cfg(root, "evaluate")  # agent.use_speed=false, anchor=none: the defaults
    policy, seed, models = policies.policy_for(cfg, "agent_r1/seed0")
    assert policy.encoder.use_speed and policy.encoder.dim == 2 * cfg.vae.latent_dim + 1
    assert (policy.action_map.anchor, policy.action_map.steer) == ("brake", "grip") and seed == 0
    rows = porav_eval.evaluate_policy(cfg, "agent_r1/seed0", porav_eval.bank(cfg)[:3], workers=1)
    assert len(rows) == 3 and all(r["actor_sha"] == models["actor_sha"] for r in rows)


def test_peer_chae_trains_and_evaluates_on_its_own_family(experiment, tmp_path, caplog):
    """pipeline peers=[chae]: Chae's DQN on its privileged state (seeds 0-2, for the evaluation's ensemble of three),
    and (found on disk) the same learner on our world model's view; then evaluate.family=chae runs the scripted
    baselines, every agent and the seed ensemble on the same trials."""
    root = tmp_path / "copy"
    shutil.copytree(experiment, root)
    train_agent.run(smoke_cfg(root, "train_agent", "agent=dqn_chae", "obs=worldmodel"))
    train_agent.run(smoke_cfg(root, "train_agent", "agent=dqn_chae_notrauma"))  # other hyperparameters: must load
    pipeline.run(smoke_cfg(root, "pipeline", "peers=[chae]"))
    runs = root / "runs/t"
    for rel in (
        "agent_chae_dqn_chae/seed0",
        "agent_chae_dqn_chae/seed1",
        "agent_chae_dqn_chae/seed2",
        "agent_chae_dqn_chae-worldmodel/seed0",
        "agent_chae_dqn_chae_notrauma/seed0",
    ):
        metrics = json.loads((runs / rel / "metrics.json").read_text())
        # smoke's 12 episodes, and blocks of 4 while the rescoring finds no member inside both bars (at most 2)
        extended = metrics.get("extended", 0)
        assert extended in (0, 4, 8) and metrics["episodes"] == 12 + extended == len(metrics["curve"]["end"])
        assert not any(g["member"] for g in metrics["curve"].get("gates", [])[:-1])
    rows = [r for r in csv.DictReader(open(runs / "eval_chae/results.csv"))]
    policies = [
        "braking",
        "ttc_braking",
        "latest_safe_braking",
        "closing_braking",
        "agent_chae_dqn_chae",
        "agent_chae_dqn_chae-worldmodel",
        "agent_chae_dqn_chae_notrauma",
        "agent_chae_dqn_chae_ensemble3",
    ]
    assert set(r["policy"] for r in rows) == set(policies)
    per_policy = {p: sum(r["policy"] == p for r in rows) for p in policies}
    trials = 3 * (3 + 1)  # 3 trials at each of 3 TTCs, and 3 in Scenario 2
    assert per_policy == {p: 3 * trials if p == "agent_chae_dqn_chae" else trials for p in policies}
    by_policy = {
        p: [(r["ttc"], r["v_init"], r["scenario"]) for r in rows if r["policy"] == p and r["policy_seed"] == "0"]
        for p in policies
    }
    assert all(v == by_policy["braking"] for v in by_policy.values())  # every policy on the same trials
    summary = json.loads((runs / "eval_chae/summary.json").read_text())
    assert set(summary["policies"]) == set(policies)
    for figure in ("stopping_distance", "bump_rate", "learning_curves"):
        assert (runs / f"eval_chae/{figure}.png").exists(), figure
    assert "Chae et al. (paper" in (runs / "eval_chae/tables.md").read_text()
    # its rows, committed, give its tables again
    published.publish(runs / "eval_chae", root / "docs/chae/validation", "pipeline peers=[chae]")
    assert recheck.recheck(root / "docs") == []
    assert not (runs / "eval/results.csv").read_text().count("chae")  # the paper's bank is left alone
    with caplog.at_level(logging.INFO, logger="worldmodel.pipeline"):
        pipeline.run(smoke_cfg(root, "pipeline", "peers=[chae]"))
    assert "running" not in caplog.text and "stale" not in caplog.text


def test_peers_merola_and_kim_train_and_the_ncap_bank_runs_every_policy(experiment, tmp_path):
    """agent=ddqn_merola on the camera, evaluate.family=merola with braking, the planner and the paper's world-model
    agents on the same trials; then one NCAP command runs every policy of every family, the car-to-car tests for
    every policy that can see a car."""
    root = tmp_path / "copy"
    shutil.copytree(experiment, root)
    for preset in ("ddqn_merola", "ddpg_kim", "ddpg_wm_kim", "dqn_chae"):
        # ddpg_wm_kim trains for its 60k steps at every scale: cut to smoke's here
        train_agent.run(smoke_cfg(root, "train_agent", f"agent={preset}", "agent.total_steps=300"))
    runs = root / "runs/t"

    # family kim: the LIDAR agent, the camera agent trained there and the paper's street agents, on the same trials
    evaluate.run(
        smoke_cfg(root, "evaluate", "evaluate.family=kim", "evaluate.kim.trials=1", "evaluate.kim.policies=[braking]")
    )
    rows = list(csv.DictReader(open(runs / "eval_kim/results.csv")))
    kim_names = ["braking", "agent_kim_unaware_ddpg_kim", "agent_kim_unaware_ddpg_wm_kim"]
    kim_names += ["agent_r1", "agent_r2", "agent_r2_chooser", "agent_r2_counterfactual"]
    assert sorted(r["policy"] for r in rows) == sorted(kim_names * 3)  # 1 trial x 3 scenarios each
    kim_trials = {p: sorted((r["scenario"], r["ego_speed"]) for r in rows if r["policy"] == p) for p in kim_names}
    assert all(t == kim_trials["braking"] for t in kim_trials.values())
    # on the sealed bank, the ledger names each agent's models: the world model for those that see through it
    kim = ("evaluate.family=kim", "evaluate.kim.trials=1", "evaluate.kim.policies=[braking]", "evaluate.bank=test")
    evaluate.run(smoke_cfg(root, "evaluate", *kim))
    (row,) = [r for r in banks.read_ledger(root / "ledger.csv") if r["family"] == "kim"]
    listed = dict(p.rstrip(")").split(" (") if " (" in p else (p, "") for p in row["policies"].split("; "))
    world_model = smoke_cfg(root, "evaluate")
    vae, rnn = artifacts.short(artifacts.vae_id(world_model)), artifacts.short(artifacts.rnn_id(world_model))
    assert listed["agent_kim_unaware_ddpg_wm_kim/seed0"].startswith(f"vae={vae}, rnn={rnn}, actor=")
    assert listed["agent_r1/seed0"].startswith(f"vae={vae}, rnn={rnn}, actor=")
    assert listed["agent_kim_unaware_ddpg_kim/seed0"].startswith("actor=")  # the LIDAR: no world model
    # and every row carries the same hashes as the ledger (scripted policies none), so it can be tied to its models
    for r in csv.DictReader(open(runs / "eval_kim_test/results.csv")):
        named = listed.get(f"{r['policy']}/seed{r['policy_seed']}", "")
        expected = dict(part.split("=") for part in named.split(", ")) if named else {}
        assert {k: r[f"{k}_sha"] for k in ("vae", "rnn", "actor") if r[f"{k}_sha"]} == expected, r["policy"]
    chae = peers_common.models_of(world_model, "agent_chae_dqn_chae_ensemble3/seed0")  # seeds 0-2; 0 trained
    assert chae == {
        "members": f"{artifacts.actor_id(world_model, artifacts.AgentId.parse('agent_chae_dqn_chae/seed0'))[:12]}+-+-"
    }
    metrics = json.loads((runs / "agent_merola_ddqn_merola/seed0/metrics.json").read_text())
    assert metrics["steps"] >= 300 and len(metrics["curve"]["return"]) == metrics["episodes"]

    evaluate.run(smoke_cfg(root, "evaluate", "evaluate.family=merola"))
    rows = list(csv.DictReader(open(runs / "eval_merola/results.csv")))
    names = ["braking", "aeb3m", "oracle", "agent_merola_ddqn_merola", "agent_r1", "agent_r2", "agent_r2_chooser"]
    names += ["agent_r2_counterfactual"]
    assert set(r["policy"] for r in rows) == set(names)
    trials = {p: [(r["scenario"], r["ego_speed"], r["ttc"]) for r in rows if r["policy"] == p] for p in names}
    assert len(trials["braking"]) == 3 * 2 and all(t == trials["braking"] for t in trials.values())
    # braking from the start always stops behind a lead car that brakes with 1-2 s of headway
    assert not any(int(r["collision"]) for r in rows if r["policy"] == "braking" and r["scenario"] == "lead_brake")
    for name in ("tables.md", "collisions.png", "learning_curves.png", "summary.json"):
        assert (runs / "eval_merola" / name).exists(), name
    for family in ("kim", "merola"):  # their rows, committed, give their tables again
        published.publish(runs / f"eval_{family}", root / f"docs/{family}/validation", "evaluate")
    assert recheck.recheck(root / "docs") == []

    ncap.run(smoke_cfg(root, "ncap", "ncap.tests=[CPNA-25]"))
    summary = json.loads((runs / "eval_ncap/summary.json").read_text())["policies"]
    car_runs = {  # 2 CCRs + 2 CCRm speeds at 100 % overlap, 4 CCRb variants; Chae's privileged policies: none
        "braking": 8,
        "oracle": 8,
        "ttc_braking": 0,
        "latest_safe_braking": 0,
        "aeb3m": 8,
        "agent_chae_dqn_chae/seed0": 0,
        "agent_kim_unaware_ddpg_kim/seed0": 8,
        "agent_merola_ddqn_merola/seed0": 8,
        "agent_r1/seed0": 8,
        "agent_r2/seed0": 8,
        "agent_r2_chooser/seed0": 8,
        "agent_r2_counterfactual/seed0": 8,
    }
    assert {k: s["car_runs"] for k, s in summary.items()} == car_runs
    assert all(s["pedestrian_runs"] == 2 for s in summary.values())  # CPNA-25 at 20 and 60 km/h
    assert summary["braking"]["pedestrian_avoided_pct"] == 100.0  # braking from TTC 1.5 s stops in time
    tables = (runs / "eval_ncap/tables.md").read_text()
    assert "CCRb 6 m/s², 12 m" in tables and (runs / "eval_ncap/ncap.png").exists()
    published.publish(runs / "eval_ncap", root / "docs/ncap/smoke", "ncap")  # its rows give its tables again
    assert recheck.recheck(root / "docs") == []
    # the bank runs after the pipeline, not in it: the experiment's stage times are not what made these rows
    assert (runs / "pipeline.json").exists() and not (root / "docs/ncap" / published.STAGE_TIMES).exists()


def test_the_local_launcher_finishes_what_a_killed_launcher_left_and_writes_what_inline_writes(experiment, tmp_path):
    """launcher=local runs each level's steps as submitit jobs on their own cores. Killed outright while its agent
    jobs run, then rerun, it waits for the jobs the first one left and finishes; its checkpoints and rows, the
    models' hashes included, are the bytes the inline pipeline writes. Both run on two threads, the default: a job
    on one core of the two keeps them (a job that trained on one thread would round the chooser's scorer
    otherwise)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    root, inline = tmp_path / "launched", tmp_path / "inline"
    for r in (root, inline):  # the same world model: the agents and the evaluation run
        shutil.copytree(experiment / "data", r / "data")
        for stage in ("vae", "rnn"):
            shutil.copytree(experiment / "runs/t" / stage, r / "runs/t" / stage)
    # two agents that train in a second or two, as two jobs on their own cores
    args = ["agents=[chooser,counterfactual]", "evaluate.policies=[braking]", "threads=2"]
    command = [sys.executable, "-m", "worldmodel.pipeline", *smoke_cfg_overrides(root), "launcher=local", *args]
    log = tmp_path / "first.log"
    with open(log, "w") as out:
        first = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, cwd=REPO)
        deadline = time.time() + 240
        while "agent_r2_counterfactual: job" not in log.read_text() and time.time() < deadline and first.poll() is None:
            time.sleep(0.2)
        assert "agent_r2_counterfactual: job" in log.read_text(), log.read_text()[-2000:]
        os.kill(first.pid, signal.SIGKILL)  # the launcher alone: its jobs go on
        first.wait()
    pipeline.run(smoke_cfg(root, "pipeline", "launcher=local", *args))
    pipeline.run(smoke_cfg(inline, "pipeline", *args))

    for agent in ("agent_r2_chooser", "agent_r2_counterfactual"):
        a, b = (r / "runs/t" / agent / "seed0/last.pt" for r in (root, inline))
        assert a.read_bytes() == b.read_bytes(), f"{agent}: the launched job's checkpoint is not the inline one's"
    launched, inlined = (read_results_csv(r / "runs/t/eval/results.csv") for r in (root, inline))
    differences = [
        (k, key, a.get(key), b.get(key))
        for k, (a, b) in enumerate(zip(launched, inlined))
        for key in sorted(set(a) | set(b))
        if repr(a.get(key)) != repr(b.get(key))
    ]
    assert len(launched) == len(inlined) > 0 and not differences, differences[:10]
    # a step the first launcher's job finished is complete on disk; it recorded no time, having been killed
    timings = json.loads((root / "runs/t/pipeline.json").read_text())
    assert "collect" not in timings and timings["eval"]["complete"]  # the world model was complete: skipped
    assert all(timings.get(f"agent_r2_{a}", {"complete": True})["complete"] for a in ("chooser", "counterfactual"))


def test_a_family_defined_in_the_tests_joins_by_one_line_per_registry_and_runs_through_the_pipeline(
    experiment, tmp_path
):
    """docs/design.md §11's steps, as tests/tiny_family.py follows them: a family whose every part is in that file
    joins the simulator, the rewards, the families and the presets by one line each, and ``peers=[tiny]`` trains
    its agent on the world model and evaluates it on its own bank; no file of the repository names it."""
    import tiny_family

    from worldmodel import registry

    root = tmp_path / "tiny"
    shutil.copytree(experiment / "data", root / "data")  # the world model: only the family's steps run
    for stage in ("vae", "rnn"):
        shutil.copytree(experiment / "runs/t" / stage, root / "runs/t" / stage)
    with tiny_family.registered():
        pipeline.run(smoke_cfg(root, "pipeline", "agents=[]", "peers=[tiny]", "banks=[validation]"))
        runs = root / "runs/t"
        assert (runs / "agent_tiny_ddpg_tiny/seed0/metrics.json").exists()
        rows = list(csv.DictReader(open(runs / "eval_tiny/results.csv")))
        assert sorted({r["policy"] for r in rows}) == ["agent_tiny_ddpg_tiny", "braking"]
        assert [r["scenario_seed"] for r in rows if r["policy"] == "braking"] == [
            r["scenario_seed"] for r in rows if r["policy"] == "agent_tiny_ddpg_tiny"
        ]
        timings = json.loads((runs / "pipeline.json").read_text())
        assert {"agent_tiny_ddpg_tiny", "eval_tiny"} <= set(timings) and "eval" not in timings
        # the shared code read it from the registry: provenance, the folder and the step are the family's own
        assert artifacts.read_provenance(runs / "eval_tiny")["inputs"].keys() == {"agent_tiny_ddpg_tiny/seed0"}
    assert "tiny" not in registry.names()
    sources = [p for d in ("worldmodel", "envs", "conf") for p in (REPO / d).rglob("*") if p.suffix in (".py", ".yaml")]
    named = [p for p in sources if "tiny" in p.read_text()]
    assert not named, named


def test_a_learner_defined_in_the_tests_joins_by_one_line_per_registry_and_is_trained_and_evaluated(
    experiment, tmp_path
):
    """docs/design.md §11's steps for a learner, as tests/tiny_learner.py follows them: a learner whose every part
    is in that file joins the learners and the presets by one line each; ``agents=[tiny_constant]`` trains it with
    train_agent and evaluates it on the paper's bank beside braking, which acts as it did in the module's run."""
    import tiny_learner

    from worldmodel import registry

    root = tmp_path / "learner"
    shutil.copytree(experiment / "data", root / "data")  # the world model: only the learner's steps run
    for stage in ("vae", "rnn"):
        shutil.copytree(experiment / "runs/t" / stage, root / "runs/t" / stage)
    with tiny_learner.registered():
        overrides = ("agents=[tiny_constant]", "banks=[validation]", "evaluate.policies=[braking]")
        pipeline.run(smoke_cfg(root, "pipeline", *overrides))
        runs = root / "runs/t"
        action = json.loads((runs / "agent_r2_tiny_constant/seed0/metrics.json").read_text())["action"]
        assert len(action) == 2 and -1.0 <= action[1] <= 1.0
        rows = read_results_csv(runs / "eval/results.csv")
        assert {r["policy"] for r in rows} == {"braking", "agent_r2_tiny_constant"}
        ours = [r for r in rows if r["policy"] == "braking"]
        module_run = [r for r in read_results_csv(experiment / "runs/t/eval/results.csv") if r["policy"] == "braking"]
        assert ours == module_run  # the same bank, and braking the same on it
        assert sum(r["policy"] == "agent_r2_tiny_constant" for r in rows) == len(ours)
    assert "tiny_constant" not in registry.LEARNERS
    sources = [p for d in ("worldmodel", "envs", "conf") for p in (REPO / d).rglob("*") if p.suffix in (".py", ".yaml")]
    assert not [p for p in sources if "tiny_constant" in p.read_text()]


# pool64, the cover's reference, renders at 16 times the area: its run stops at the world model, and the cover's run
# takes the learners on.
@pytest.mark.parametrize(
    ("view", "key", "value", "agents"),
    [("cover64", "road_user_cover", True, "[chooser,counterfactual]"), ("pool64", "supersample", 4, "[]")],
)
def test_a_view_flows_through_every_stage(experiment, tmp_path, view, key, value, agents):
    """A view other than the paper's from an empty experiment: the recorded frames are the paper's frames with road
    users drawn more fully (the same episodes, so every other pixel is equal), the labels live in a store of their
    own, and the world model, the chooser, the counterfactual actor and the evaluation run on them."""
    from envs.scene import PEDESTRIANS, VEHICLES
    from worldmodel.data import RolloutStore

    root = tmp_path / view
    pipeline.run(smoke_cfg(root, "pipeline", f"view={view}", f"agents={agents}", "banks=[validation]"))
    settings = json.loads((root / "data/t/rollouts/collect_config.json").read_text())
    assert settings["env"][key] == value
    paper_settings = json.loads((experiment / "data/t/rollouts/collect_config.json").read_text())
    assert key not in paper_settings["env"]
    view_store, paper_store = RolloutStore(root / "data/t/rollouts"), RolloutStore(experiment / "data/t/rollouts")
    more = 0
    for i in sorted(paper_store.lengths):
        frames, paper = view_store.read(i, "seg"), paper_store.read(i, "seg")
        others = ~np.isin(frames, (PEDESTRIANS, VEHICLES)) & ~np.isin(paper, (PEDESTRIANS, VEHICLES))
        agree = (frames[others] == paper[others]).mean()
        assert agree == 1.0 if view == "cover64" else agree > 0.999  # a 4x render may differ on a rare edge pixel
        more += int(np.isin(frames, (PEDESTRIANS, VEHICLES)).sum() - np.isin(paper, (PEDESTRIANS, VEHICLES)).sum())
    assert more > 0
    assert (root / "runs/t/vae/best.pt").exists() and (root / "runs/t/rnn/best.pt").exists()
    if agents == "[]":
        return
    rows = read_results_csv(root / "runs/t/eval/results.csv")
    labels = {p.name for p in (root / "data/t/chooser_labels").iterdir()}
    assert labels.isdisjoint(p.name for p in (experiment / "data/t/chooser_labels").iterdir())
    assert {r["policy"] for r in rows} == {"braking", "oracle", "agent_r2_chooser", "agent_r2_counterfactual"}
    paper_rows = read_results_csv(experiment / "runs/t/eval/results.csv")
    vae_sha = {r["vae_sha"] for r in rows if r["vae_sha"]}
    assert vae_sha and vae_sha.isdisjoint(r["vae_sha"] for r in paper_rows)
