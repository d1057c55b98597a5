"""The pipeline's steps as submitit jobs: ``launcher=local`` (processes on this machine, each on its own share of
the cores) or ``launcher=slurm`` (each step a SLURM job, resources from ``conf/hydra/launcher/slurm.yaml``).

The steps fall into levels by what they read (docs/design.md §9): the collection, then the VAE, the LSTM, the
demonstrations, every agent, every evaluation. A level's steps read only what earlier levels wrote, so they run
at once; the launcher submits the ready ones (at most ``launcher_jobs`` at a time), waits, and goes on to the next
level. Each step decides, as in the inline pipeline, whether it is complete (skipped), stale (set aside, rebuilt) or
to be continued, so a launcher that stopped resumes by running it again. A job that fails stops the run once its
level's other jobs end, naming its log. A job left running by a launcher that was killed holds its folder's lock:
the next launcher waits for it before looking at that step again.

Jobs leave their pickles and logs in ``runs/NAME/launcher/<job id>/``.
"""

from __future__ import annotations

import logging
import os
import resource
import shutil
import time
from pathlib import Path

from omegaconf import OmegaConf

from . import artifacts
from .common import CONF_DIR, LockHeldError, StageError, lock_holder

log = logging.getLogger(__name__)

LEVELS = ("collect", "vae", "rnn", "demos", "agent", "eval")  # a step reads only what the levels before it wrote
NEVER_S = 7 * 24 * 60  # submitit's local jobs stop at their time limit (5 minutes unless told): a week


def levels(steps: list) -> list[list]:
    """The steps grouped by ``LEVELS``, in the pipeline's order within each."""
    return [[s for s in steps if s.kind == kind] for kind in LEVELS if any(s.kind == kind for s in steps)]


def run_step(run, cfg, cpus: list[int] | None, output: Path | None = None, marker: Path | None = None) -> dict:
    """A job's body: the stage's ``run(cfg)`` on ``cpus`` (its share of the machine, so that worker counts left at
    auto follow it), with its wall time and the peak memory of its process and workers. The stage keeps its
    configured ``threads`` on a smaller share: torch splits a sum or a product by thread, so the count decides the
    last bits of a trained model, and a job then writes the bytes the inline pipeline writes (docs/design.md §9);
    two threads taking turns on one core cost nothing measurable (benchmarks/RESULTS.md).

    The job holds ``output``'s writer lock from before it looks at ``marker`` until the stage ends, and skips the
    stage when the marker is there: a job that a killed launcher submitted can start after the next launcher's job
    for the same step has finished it, and must then leave its files as they are (``skipped``)."""
    from contextlib import nullcontext

    from .common import writer_lock

    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    if cpus:
        os.sched_setaffinity(0, cpus)
    t0 = time.perf_counter()
    with writer_lock(output, "the launcher's step") if output is not None else nullcontext():
        if marker is not None and Path(marker).exists():
            return {"stopped": False, "skipped": True, "wall_s": 0.0, "peak_rss_mb": 0.0}
        result = run(cfg)
    own, workers = (
        resource.getrusage(who).ru_maxrss / 1024 for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    return {
        "stopped": isinstance(result, dict) and bool(result.get("stopped")),
        "wall_s": time.perf_counter() - t0,
        "peak_rss_mb": own + workers,
    }


SLURM_COMMANDS = ("sbatch", "srun")  # submitit looks for srun when it starts and submits each job with sbatch


def check_reachable(cfg) -> None:
    """A StageError when ``launcher=slurm`` but SLURM's commands are not on PATH: said before any step runs, rather
    than as submitit's traceback once the run has begun."""
    if cfg.launcher != "slurm":
        return
    missing = [c for c in SLURM_COMMANDS if shutil.which(c) is None]
    if not missing:
        return
    raise StageError(
        f"launcher=slurm submits each step as a SLURM job, but {' and '.join(missing)} "
        f"{'is' if len(missing) == 1 else 'are'} not on PATH here: run on a machine of the SLURM cluster (where "
        "`sbatch --version` and `sinfo` answer), or run on this machine with launcher=local (the steps as processes "
        "here, launcher_jobs at once) or without a launcher setting (launcher=inline, one step after another)"
    )


def executor(cfg, folder: Path):
    """The submitit executor of ``cfg.launcher``."""
    import submitit

    check_reachable(cfg)
    if cfg.launcher == "local":
        ex = submitit.LocalExecutor(folder=folder)
        ex.update_parameters(timeout_min=NEVER_S)
        return ex
    slurm = OmegaConf.load(CONF_DIR / "hydra" / "launcher" / "slurm.yaml")
    ex = submitit.AutoExecutor(folder=folder, cluster="slurm")
    ex.update_parameters(
        timeout_min=int(slurm.timeout_min),
        cpus_per_task=int(slurm.cpus_per_task),
        mem_gb=int(slurm.mem_gb),
        nodes=1,
        tasks_per_node=1,
        **({"slurm_partition": slurm.partition} if slurm.partition else {}),
        **({"slurm_account": slurm.account} if slurm.account else {}),
        **({"gpus_per_node": int(slurm.gpus_per_node)} if slurm.gpus_per_node else {}),
    )
    return ex


def core_shares(jobs: int) -> list[list[int]]:
    """This process's cores cut into ``jobs`` shares, one per job running at once (at least one core each)."""
    cores = sorted(os.sched_getaffinity(0))
    jobs = max(1, min(jobs, len(cores)))
    return [cores[k::jobs] for k in range(jobs)]


def launch(cfg, planned: list, prepare, record) -> bool:
    """Run the pipeline's ``planned`` steps as jobs, level by level. ``prepare(step)`` returns the step's config when
    it has to run (after setting a stale one aside) or None when it is complete; ``record(step, outcome)`` keeps its
    time. Returns False when a step was stopped by a signal (the pipeline then stops, as inline)."""
    folder = artifacts.runs_root(cfg) / "launcher"
    ex = executor(cfg, folder)
    local = cfg.launcher == "local"
    width = int(cfg.launcher_jobs)
    for level in levels(planned):
        # a level of fewer steps than launcher_jobs (the collection, the demonstrations, one evaluation) shares the
        # cores among the steps it has, so that a lone step gets them all, as inline
        shares = core_shares(min(width, len(level))) if local else []
        waiting, running, failed, stopped = list(level), [], [], False
        while waiting or running:
            while waiting and len(running) < (len(shares) if local else width):
                step = waiting.pop(0)
                changed = OmegaConf.merge(cfg, step.changes)
                holder = lock_holder(artifacts.output_dir(changed, step.kind, step.agent))
                if holder is not None:  # a job of a launcher that was stopped still writes it
                    log.info("[launcher] %s: waiting for %s, which still writes it", step.name, holder)
                    waiting.append(step)
                    time.sleep(0.2)
                    break
                stage_cfg = prepare(step)
                if stage_cfg is None:
                    continue
                cpus = None
                if local:  # a share no running job holds; its threads stay as configured (``run_step``)
                    cpus = next(share for share in shares if all(share is not c for _, _, c in running))
                output = artifacts.output_dir(stage_cfg, step.kind, step.agent)
                marker = artifacts.marker(stage_cfg, step.kind, step.agent)
                job = ex.submit(run_step, step.run, stage_cfg, cpus, output, marker)
                log.info("[launcher] %s: job %s%s", step.name, job.job_id, f" on cores {cpus}" if cpus else "")
                running.append((step, job, cpus))
            for entry in [r for r in running if r[1].done()]:
                step, job, _ = entry
                running.remove(entry)
                try:
                    outcome = job.result()
                except Exception as err:  # the job's own traceback is in its log
                    if LockHeldError.__name__ in str(err):
                        waiting.insert(0, step)  # a job an earlier launcher left took the folder first: look again
                    else:
                        failed.append(f"{step.name} (log: {job.paths.stderr})")
                    continue
                if not outcome.get("skipped"):  # skipped: another launcher's job had finished it
                    record(step, outcome)
                stopped |= outcome["stopped"]
            time.sleep(0.2)
        if failed:
            raise StageError(
                f"the launcher's job for {'; '.join(failed)} failed; the steps that finished are kept: fix the cause "
                "and run the pipeline again to continue"
            )
        if stopped:
            return False
    return True
