"""The whole pipeline in order: collect, VAE, LSTM, agents R1 and R2, evaluation.

    python -m worldmodel.pipeline experiment=NAME scale=smoke|quick|paper

Stages whose outputs are complete are skipped; the others run with ``resume=true``, so an interrupted pipeline
continues where it stopped. Each stage's wall time and peak memory (this process and its workers, sampled
every 0.2 s) are written to ``runs/NAME/pipeline.json``.
"""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

from omegaconf import OmegaConf

from .common import atomic_write_text, data_dir, hydra_main, runs_dir


class PeakMemory:
    """Samples the resident memory of this process and its children in a background thread."""

    def __init__(self, interval: float = 0.2):
        import psutil

        self._proc = psutil.Process()
        self.interval, self.peak_mb = interval, 0.0
        self._stop = threading.Event()

    def _sample(self) -> float:
        total = 0
        for p in [self._proc, *self._proc.children(recursive=True)]:
            try:
                total += p.memory_info().rss
            except Exception:  # a worker that just exited
                pass
        return total / 2**20

    def _loop(self):
        while not self._stop.is_set():
            self.peak_mb = max(self.peak_mb, self._sample())
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        return False


def stages(cfg) -> list[tuple[str, Path, callable, dict]]:
    """(name, completion marker, run function, config changes) in pipeline order."""
    from . import collect, evaluate, train_agent, train_rnn, train_vae

    return [
        ("collect", data_dir(cfg) / "rollouts" / "manifest.json", collect.run, {}),
        ("vae", runs_dir(cfg, "vae") / "metrics.json", train_vae.run, {}),
        ("rnn", runs_dir(cfg, "rnn") / "metrics.json", train_rnn.run, {}),
        ("agent_r1", train_agent.agent_dir(cfg, "r1") / "metrics.json", train_agent.run, {"reward": {"name": "r1"}}),
        ("agent_r2", train_agent.agent_dir(cfg, "r2") / "metrics.json", train_agent.run, {"reward": {"name": "r2"}}),
        ("eval", runs_dir(cfg, "eval") / "summary.json", evaluate.run, {}),
    ]


def run(cfg) -> dict:
    timing_path = Path(cfg.paths.runs) / "pipeline.json"
    timings = json.loads(timing_path.read_text()) if timing_path.exists() else {}
    t_all = time.perf_counter()
    for name, marker, stage_run, changes in stages(cfg):
        if marker.exists():
            print(f"[pipeline] {name}: complete ({marker}), skipped")
            continue
        print(f"[pipeline] {name}: running")
        stage_cfg = OmegaConf.merge(cfg, {"resume": True}, changes)
        t0 = time.perf_counter()
        with PeakMemory() as mem:
            result = stage_run(stage_cfg)
        if isinstance(result, dict) and result.get("stopped"):
            print(f"[pipeline] {name} was interrupted; rerun the pipeline to continue.")
            return timings
        timings[name] = {"wall_s": round(time.perf_counter() - t0, 1), "peak_rss_mb": round(mem.peak_mb, 1),
                         "scale": OmegaConf.select(cfg, "scale_name", default=None)}
        atomic_write_text(timing_path, json.dumps(timings, indent=2))
    ev = runs_dir(cfg, "eval")
    print(f"[pipeline] done in {time.perf_counter() - t_all:.0f} s (this run). Stage times: {timing_path}\n"
          f"  tables:   {ev / 'tables.md'}\n  heatmaps: {ev / 'heatmaps.png'}\n  summary:  {ev / 'summary.json'}\n"
          f"  TensorBoard: .venv/bin/tensorboard --logdir {cfg.paths.runs}")
    return timings


main = hydra_main("pipeline")(run)

if __name__ == "__main__":
    main()
