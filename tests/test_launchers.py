"""Multirun through the real Hydra launcher plugins (conf/hydra/launcher/): submitit, joblib, and SLURM's sbatch.

Each test runs the real collection stage as a command, sweeping seed=0,1 at scale=smoke into tmp_path. The
two jobs write to different datasets through ``paths.data=${paths.data_root}/sweep_s${seed}`` (interpolated
per job), while both share one experiment and so one sweep dir, runs/sweep/hydra/multirun/<time>/.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

from worldmodel.collect import episode_spec
from worldmodel.data import RolloutStore, validate

REPO = Path(__file__).resolve().parent.parent
SEEDS = (0, 1)


def sweep(tmp_path: Path, *overrides: str, env: dict | None = None, workers: int = 1) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "worldmodel.collect",
        "-m",
        *overrides,
        "experiment=sweep",
        "paths.data=${paths.data_root}/sweep_s${seed}",
        "seed=0,1",
        "scale=smoke",
        f"collect.num_workers={workers}",
        f"paths.data_root={tmp_path}/data",
        f"paths.runs_root={tmp_path}/runs",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=240)


def the_sweep_dir(tmp_path: Path) -> Path:
    dirs = list((tmp_path / "runs" / "sweep" / "hydra" / "multirun").iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


def check_datasets(tmp_path: Path) -> None:
    """One complete, valid dataset per seed, each drawn from its own seed's scenarios."""
    frames = {}
    for seed in SEEDS:
        root = tmp_path / "data" / f"sweep_s{seed}" / "rollouts"
        assert validate(root) == (4, sum(json.loads((root / "manifest.json").read_text())["lengths"].values()))
        assert json.loads((root / "collect_config.json").read_text())["seed"] == seed
        store = RolloutStore(root)
        assert sorted(set(store.location) - set(store.branch_of)) == [0, 1, 2, 3]
        assert [int(store.attrs(i)["seed"]) for i in range(4)] == [episode_spec(seed, i).seed for i in range(4)]
        frames[seed] = store.read(0, "seg")
        store.close()
    s0, s1 = frames[0], frames[1]
    assert s0.shape != s1.shape or not np.array_equal(s0, s1), "both seeds recorded the same frames"
    assert {episode_spec(0, i).seed for i in range(4)}.isdisjoint({episode_spec(1, i).seed for i in range(4)})


def job_records(sweep_dir: Path) -> dict[int, dict]:
    """hydra.yaml of each job subdir, by seed."""
    out = {}
    for n in (0, 1):
        hydra_cfg = yaml.safe_load((sweep_dir / str(n) / ".hydra" / "hydra.yaml").read_text())["hydra"]
        seed = int(next(o for o in hydra_cfg["overrides"]["task"] if o.startswith("seed=")).split("=")[1])
        out[seed] = hydra_cfg
    assert sorted(out) == list(SEEDS)
    return out


def test_submitit_local_sweep_runs_each_seed_as_a_submitit_job(tmp_path):
    # two collection workers inside each job: the stage's process pool must work under a launcher too
    result = sweep(tmp_path, "hydra/launcher=submitit_local", workers=2)
    assert result.returncode == 0, result.stderr[-3000:]
    check_datasets(tmp_path)

    sweep_dir = the_sweep_dir(tmp_path)
    assert sweep_dir.resolve().is_relative_to(tmp_path.resolve())
    jobs = job_records(sweep_dir)
    submitit_dir = sweep_dir / ".submitit"
    for seed, hydra_cfg in jobs.items():
        assert hydra_cfg["runtime"]["choices"]["hydra/launcher"] == "submitit_local"
        # The job id Hydra recorded is submitit's, and submitit kept that job's logs in the sweep dir.
        job_id = str(hydra_cfg["job"]["id"])
        text = (submitit_dir / job_id / f"{job_id}_0_log.out").read_text()  # <job id>_<task rank>_log.out
        assert "Job completed successfully" in text
        assert f"[collect] {tmp_path}/data/sweep_s{seed}/rollouts: 4 episodes" in text
        assert list((submitit_dir / job_id).glob("*_result.pkl"))


def test_joblib_sweep_runs_two_jobs_at_once(tmp_path):
    result = sweep(tmp_path, "hydra/launcher=local")
    assert result.returncode == 0, result.stderr[-3000:]
    check_datasets(tmp_path)

    sweep_dir = the_sweep_dir(tmp_path)
    multirun = yaml.safe_load((sweep_dir / "multirun.yaml").read_text())["hydra"]
    assert multirun["launcher"]["_target_"].endswith("JoblibLauncher") and multirun["launcher"]["n_jobs"] == 2
    for seed, hydra_cfg in job_records(sweep_dir).items():
        assert hydra_cfg["runtime"]["choices"]["hydra/launcher"] == "local"
        assert str(hydra_cfg["job"]["id"]).endswith(f"_{seed}")  # joblib's "<job name>_<index>", set in the job
    assert not (sweep_dir / ".submitit").exists()


def test_slurm_launcher_writes_the_documented_sbatch_script(tmp_path):
    """No cluster here: fake `srun` and `sbatch` (which keeps the script and refuses the job) stand in."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = tmp_path / "submitted.sbatch"
    (bin_dir / "sbatch").write_text(f'#!/bin/sh\ncp "$1" {script}\necho "sbatch: fake, refused" >&2\nexit 1\n')
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 1\n")
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    result = sweep(
        tmp_path,
        "hydra/launcher=slurm",
        "hydra.launcher.partition=testq",
        env={"PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"},
    )
    assert result.returncode != 0 and "sbatch: fake, refused" in result.stderr, result.stderr[-3000:]
    assert not (tmp_path / "data").exists(), "a job ran without SLURM"

    lines = script.read_text().splitlines()
    sbatch = dict(line[len("#SBATCH --") :].split("=", 1) for line in lines if line.startswith("#SBATCH --"))
    assert sbatch["partition"] == "testq"
    assert sbatch["cpus-per-task"] == "2" and sbatch["mem"] == "8GB" and sbatch["time"] == "240"
    assert sbatch["nodes"] == "1" and sbatch["ntasks-per-node"] == "1"
    assert sbatch["array"] == "0-1%2"  # one array task per seed
    assert sbatch["job-name"] == "collect"
    assert not [k for k in sbatch if "gpu" in k or k == "gres"], "a CPU-only job must not ask for a GPU"
    assert sbatch["output"].startswith(str(the_sweep_dir(tmp_path) / ".submitit") + "/")
    assert f"{sys.executable} -u -m submitit.core._submit" in lines[-1]


def test_pipeline_launcher_slurm_without_slurm_says_what_works_here_before_any_step(tmp_path):
    """launcher=slurm on a machine without SLURM's commands stops at once with one sentence naming the setting, the
    launchers that work here and how to check for SLURM, rather than submitit's traceback after the lock is taken."""
    path = os.pathsep.join(
        d for d in os.environ["PATH"].split(os.pathsep) if not any((Path(d) / c).exists() for c in ("sbatch", "srun"))
    )
    cmd = [
        sys.executable,
        "-m",
        "worldmodel.pipeline",
        "experiment=smk",
        "scale=smoke",
        "launcher=slurm",
        f"paths.data_root={tmp_path}/data",
        f"paths.runs_root={tmp_path}/runs",
        f"paths.ledger={tmp_path}/ledger.csv",
    ]
    env = {**os.environ, "PATH": path, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    said = result.stdout + result.stderr
    assert result.returncode == 2, said[-3000:]
    assert "Traceback" not in said and "launcher=slurm" in said and "launcher=local" in said, said[-3000:]
    assert "sbatch --version" in said, said[-3000:]
    assert not (tmp_path / "data").exists(), "a step ran before the launcher was checked"
    assert not (tmp_path / "runs/smk/pipeline.json").exists()
