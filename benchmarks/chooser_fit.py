"""Time the two-camera chooser's stage by phase (labelling, encoding with the frame band, fitting the scorer) and
record its peak memory and what it produced, so that two versions can be held to the same labels and scorer.

    python -m benchmarks.chooser_fit OUT.json experiment=quick scale=quick agent.chooser.episodes=1500 \\
        agent.chooser.steps=500

The overrides go to the ``train_agent`` config with ``agent=chooser_tele``. ``REPLICATE=N`` in the environment
tiles the labels N times (as N times the episodes, the same frames) before the inputs are built: the memory of a
paper-scale fit from a small labelling. Labels already on disk are read, not
made again: delete ``data/NAME/chooser_labels/`` to time the labelling. ``OUT.json`` gets each phase's seconds, the
process's peak resident memory, the SHA-256 of the labels' arrays and of the fitted scorer's weights, and the scorer
itself is saved beside it (``OUT.pt``).
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch


def digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for key in sorted(arrays):
        h.update(key.encode())
        h.update(np.ascontiguousarray(arrays[key]).tobytes())
    return h.hexdigest()


def peak_mb() -> int:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def main(out: str, *overrides: str) -> None:
    from worldmodel import chooser, loading
    from worldmodel.common import seed_everything, set_threads
    from worldmodel.config import compose, validate

    cfg = compose("train_agent", ["agent=chooser_tele", *overrides])
    typed = validate(cfg)
    c = typed.agent.chooser
    set_threads(typed.threads)
    seed_everything(typed.seed)
    times = {}
    t0 = time.perf_counter()
    data = chooser.labels(cfg)
    times["labels_s"] = time.perf_counter() - t0
    peaks = {"labels": peak_mb()}
    labels_sha = digest({k: v for k, v in data.items()})
    copies = int(os.environ.get("REPLICATE", "1"))
    if copies > 1:
        span = int(data["episode"].max()) + 1
        tiled = {k: [v + n * span if k == "episode" else v for n in range(copies)] for k, v in data.items()}
        data = {k: np.concatenate(v) for k, v in tiled.items()}
        del tiled
    t0 = time.perf_counter()
    encoder = loading.load_world_model(cfg)
    steps = chooser.decide_steps_for(c.decide_s, typed.env.step_s)
    x = chooser.scorer_inputs(encoder, data, steps, c.mask_view, c.mask_camera)
    times["inputs_s"] = time.perf_counter() - t0
    for frames in ("seg", chooser.TELE_KEY):  # as the stage does once the inputs hold them
        data.pop(frames, None)
    peaks["inputs"] = peak_mb()
    y = data["costs"].astype(np.float32)
    y_fit = y + np.float32(c.static_penalty) * data[chooser.STATIC_KEY] if c.static_penalty > 0 else y
    t0 = time.perf_counter()
    scorer, history = chooser.fit_scorer(x, y_fit, data["episode"], c, typed.seed, state=data["state"])
    times["fit_s"] = time.perf_counter() - t0
    state = scorer.state_dict()
    scorer_sha = digest({k: v.numpy() for k, v in state.items()})
    torch.save(state, Path(out).with_suffix(".pt"))
    record = {
        **{k: round(v, 1) for k, v in times.items()},
        "peak_rss_mb": peak_mb(),
        "peak_rss_mb_by_phase": peaks,
        "labelled_states": int(len(y)),
        "labels_sha256": labels_sha,
        "scorer_sha256": scorer_sha,
        "history": history,
    }
    Path(out).write_text(json.dumps(record, indent=1))
    print(json.dumps({k: v for k, v in record.items() if k != "history"}, indent=1))


if __name__ == "__main__":
    main(*sys.argv[1:])
