"""Phase 0 (collection) and phase 1 (VAE training): throughput and peak memory, each stage run as it is used.

    python -m benchmarks.bench_stages [--episodes 96] [--max-episode-s 8.0] [--vae-epochs 1] [--tiny]

Every run is a fresh subprocess of the real command (``python -m worldmodel.collect ...`` /
``python -m worldmodel.train_vae ...``) at ``scale=smoke`` with size overrides, into a temporary directory, so
the numbers include what a user pays: interpreter and torch start-up, Hydra, the worker pool, HDF5 I/O.

* Collection, ``collect.num_workers`` = 1 and 2 on the same episodes (same seed, so the same frames).
  frames = ``manifest.json`` -> ``summary.frames`` (every recorded observation, reset frames included).
* VAE training, ``threads`` = 1 and 2 on the 1-worker collection. frames = epochs x frames of the training
  split; the stage's own ``metrics.json`` -> ``train_frames_per_s`` is reported beside the wall-clock rate.

Memory, two ways: ``max_rss_mb`` is ``ru_maxrss`` from ``os.wait4`` on the stage, i.e. the largest single
process of the tree (Linux folds reaped descendants into it as a max, not a sum; a bare launcher process does
the wait4 so the figure is not inflated by this benchmark's own size); ``tree_peak_rss_mb`` is the largest SUM
of RSS over the stage and all its descendants, sampled with psutil every 0.1 s (it can miss a spike shorter
than that, and counts shared pages once per process).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from .common import write

PROJECT_ROOT = Path(__file__).resolve().parent.parent
SAMPLE_S = 0.1


# A minimal process between this benchmark and the stage. Linux charges a process's ru_maxrss with the address
# space it had before exec(), which after fork/vfork is the PARENT's: a stage spawned straight from this (possibly
# large) benchmark process would report at least our own RSS. So a bare interpreter spawns the stage and reports
# the stage's wait4() rusage (its own peak, and that of its reaped workers as a max) and its wall time.
LAUNCHER = """
import json, os, sys, time
t0 = time.perf_counter()
pid = os.posix_spawn(sys.argv[2], sys.argv[2:], os.environ)
_, status, ru = os.wait4(pid, 0)
wall = time.perf_counter() - t0
code = os.waitstatus_to_exitcode(status)
with open(sys.argv[1], "w") as fh:
    json.dump({"wall_s": wall, "maxrss_kb": ru.ru_maxrss, "utime": ru.ru_utime, "stime": ru.ru_stime,
               "code": code}, fh)
sys.exit(code if code >= 0 else 1)
"""


class TreeSampler(threading.Thread):
    """Samples the summed RSS of a process's descendants (not the process itself) until stopped."""

    def __init__(self, pid: int, interval: float = SAMPLE_S):
        super().__init__(daemon=True)
        self.pid, self.interval = pid, interval
        self.peak_bytes, self.peak_processes, self.samples = 0, 0, 0
        self._stop_event = threading.Event()

    def run(self) -> None:
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.NoSuchProcess:
            return
        while not self._stop_event.is_set():
            total, count = 0, 0
            try:
                procs = root.children(recursive=True)
            except psutil.NoSuchProcess:
                break
            for p in procs:
                try:
                    total += p.memory_info().rss
                    count += 1
                except (psutil.NoSuchProcess, psutil.ZombieProcess, psutil.AccessDenied):
                    pass
            self.samples += 1
            if total > self.peak_bytes:
                self.peak_bytes, self.peak_processes = total, count
            self._stop_event.wait(self.interval)

    def stop(self) -> None:
        self._stop_event.set()
        self.join()


def run_stage(module: str, overrides: list[str], log_path: Path, tmp: Path) -> dict:
    """Run ``python -m module overrides...``; wall time and peak memory of the whole process tree."""
    cmd = [sys.executable, "-m", module, *overrides]
    usage_path = log_path.with_suffix(".usage.json")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open(log_path, "wb") as log:
        # Own process group, so an interrupted benchmark can stop the stage together with its pool workers.
        proc = subprocess.Popen(
            [sys.executable, "-c", LAUNCHER, str(usage_path), *cmd],
            cwd=PROJECT_ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        sampler = TreeSampler(proc.pid)  # the stage and its workers, without the launcher
        sampler.start()
        try:
            proc.wait()
        except BaseException:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
            raise
        finally:
            sampler.stop()
    if proc.returncode != 0 or not usage_path.exists():
        tail = log_path.read_text(errors="replace")[-3000:]
        raise RuntimeError(f"`{' '.join(cmd[1:])}` exited with {proc.returncode}; log tail:\n{tail}")
    usage = json.loads(usage_path.read_text())
    return {
        "command": " ".join(["python", *cmd[1:]]).replace(str(tmp), "<tmp>"),
        "wall_s": round(usage["wall_s"], 3),
        "max_rss_mb": round(usage["maxrss_kb"] / 1024.0, 1),
        "tree_peak_rss_mb": round(sampler.peak_bytes / 2**20, 1),
        "tree_processes_at_peak": sampler.peak_processes,
        "rss_samples": sampler.samples,
        "user_cpu_s": round(usage["utime"], 2),
        "sys_cpu_s": round(usage["stime"], 2),
    }


def common_overrides(tmp: Path, tag: str) -> list[str]:
    return [
        "experiment=bench",
        f"paths.data_root={tmp / tag / 'data'}",
        f"paths.runs_root={tmp / tag / 'runs'}",
        "scale=smoke",
    ]


def collect_run(tmp: Path, workers: int, episodes: int, max_episode_s: float) -> tuple[dict, Path]:
    tag = f"collect_w{workers}"
    overrides = common_overrides(tmp, tag) + [
        f"collect.episodes={episodes}",
        "collect.episodes_per_shard=2",
        f"collect.max_episode_s={max_episode_s}",
        f"collect.num_workers={workers}",
    ]
    res = run_stage("worldmodel.collect", overrides, tmp / f"{tag}.log", tmp)
    rollouts = tmp / tag / "data" / "bench" / "rollouts"
    summary = json.loads((rollouts / "manifest.json").read_text())["summary"]
    res.update(
        {
            "num_workers": workers,
            "episodes": summary["episodes"],
            "frames": summary["frames"],
            "frames_per_s": round(summary["frames"] / res["wall_s"], 1),
            "frames_per_s_in_stage": summary.get("frames_per_s_this_run"),
            "stage_wall_s": summary.get("wall_s"),
        }
    )
    print(
        f"[stages] collect workers={workers}: {res['frames']} frames in {res['wall_s']:.1f} s -> "
        f"{res['frames_per_s']:.0f} frames/s (in-stage {res['frames_per_s_in_stage']}), "
        f"tree peak {res['tree_peak_rss_mb']:.0f} MB"
    )
    return res, tmp / tag / "data"


def train_frames(rollouts: Path) -> int:
    manifest = json.loads((rollouts / "manifest.json").read_text())
    split = json.loads((rollouts / "split.json").read_text())
    return int(sum(manifest["lengths"][str(i)] for i in split["train"]))


def vae_run(tmp: Path, data_root: Path, threads: int, epochs: int, batch_size: int) -> dict:
    tag = f"vae_t{threads}"
    overrides = [
        "experiment=bench",
        f"paths.data_root={data_root}",
        f"paths.runs_root={tmp / tag / 'runs'}",
        "scale=smoke",
        f"vae.epochs={epochs}",
        f"vae.batch_size={batch_size}",
        f"threads={threads}",
    ]
    res = run_stage("worldmodel.train_vae", overrides, tmp / f"{tag}.log", tmp)
    frames = epochs * train_frames(data_root / "bench" / "rollouts")
    metrics = json.loads((tmp / tag / "runs" / "bench" / "vae" / "metrics.json").read_text())
    res.update(
        {
            "threads": threads,
            "epochs": epochs,
            "batch_size": batch_size,
            "train_frames": frames,
            "frames_per_s": round(frames / res["wall_s"], 1),
            "frames_per_s_in_stage": metrics.get("train_frames_per_s"),
        }
    )
    print(
        f"[stages] vae threads={threads}: {frames} train frames in {res['wall_s']:.1f} s -> "
        f"{res['frames_per_s']:.0f} frames/s (in-stage {res['frames_per_s_in_stage']}), "
        f"tree peak {res['tree_peak_rss_mb']:.0f} MB"
    )
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    # 96: about 5 s of collection for one worker, so that the workers' start-up does not hide the speed-up of two
    ap.add_argument("--episodes", type=int, default=96, help="episodes collected per run")
    ap.add_argument("--max-episode-s", type=float, default=8.0, help="episode length cap, seconds (15 FPS)")
    ap.add_argument("--vae-epochs", type=int, default=1)
    ap.add_argument("--vae-batch-size", type=int, default=32)
    ap.add_argument(
        "--tiny",
        action="store_true",
        help="seconds-long check that the benchmark works (not a measurement): 4 episodes of 1 s",
    )
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory (logs, data) and print it")
    args = ap.parse_args(argv)
    if args.tiny:
        args.episodes, args.max_episode_s, args.vae_epochs = 4, 1.0, 1

    tmp = Path(tempfile.mkdtemp(prefix="bench_stages_"))
    load = os.getloadavg()
    try:
        collect = {}
        data_root = None
        for workers in (1, 2):
            res, root = collect_run(tmp, workers, args.episodes, args.max_episode_s)
            collect[f"workers_{workers}"] = res
            data_root = data_root or root
        if collect["workers_1"]["frames"] != collect["workers_2"]["frames"]:
            print("[stages] warning: 1- and 2-worker collections recorded different frame counts", file=sys.stderr)
        c1, c2 = collect["workers_1"], collect["workers_2"]
        collect["speedup_2_vs_1"] = round(c2["frames_per_s"] / c1["frames_per_s"], 3)
        vae = {f"threads_{t}": vae_run(tmp, data_root, t, args.vae_epochs, args.vae_batch_size) for t in (1, 2)}
        vae["speedup_2_vs_1"] = round(vae["threads_2"]["frames_per_s"] / vae["threads_1"]["frames_per_s"], 3)
    finally:
        if args.keep:
            print(f"[stages] kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)

    peak = {
        "collect": max(c1["tree_peak_rss_mb"], c2["tree_peak_rss_mb"]),
        "vae": max(vae["threads_1"]["tree_peak_rss_mb"], vae["threads_2"]["tree_peak_rss_mb"]),
    }
    result = {
        "tiny": bool(args.tiny),
        "params": {
            "episodes": args.episodes,
            "max_episode_s": args.max_episode_s,
            "vae_epochs": args.vae_epochs,
            "vae_batch_size": args.vae_batch_size,
            "scale": "smoke",
            "episodes_per_shard": 2,
        },
        "command": " ".join(["python -m benchmarks.bench_stages", *(argv if argv is not None else sys.argv[1:])]),
        "loadavg_at_start": [round(x, 2) for x in load],
        "collect": collect,
        "vae": vae,
        "peak_tree_rss_mb": peak,
    }
    print(write("stages", result))
    return result


if __name__ == "__main__":
    main()
