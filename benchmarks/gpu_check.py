"""The GPU check: does the pipeline run on CUDA, and how much faster does it train there than on the CPU?

    python -m benchmarks.gpu_check                       # on a GPU machine: CUDA against the CPU, about 5 minutes
    python -m benchmarks.gpu_check --device cpu --tiny   # the CPU half only, seconds (the test suite runs this)

1. the smoke pipeline, end to end, with ``device=<device>`` (``--no-pipeline`` skips it);
2. VAE and LSTM training steps at the paper-scale batch (``conf/scale/paper.yaml``) on synthetic batches of the
   real shapes, on the device and on the CPU with all its cores and with two (the reference machine's count), and
   on CUDA also at ``scale=paper_gpu``'s larger batch: frames per second each. ``speedup`` sets the device at that
   batch against two cores, the pipeline's goal of twenty times;
3. 1,000 DDPG updates at the agent's batch and 1,000 single decisions of its actor (batch of 1), on each;
4. 1,000 whole decisions (frame -> VAE -> LSTM -> actor, batch of 1) on each: the CPU's fast path against the
   module path on the device, the number that ``decision_device`` is chosen by.

Writes one JSON file: ``$OUT/gpu_check.json`` when ``OUT`` is set (the lent GPU machine's output folder), else
``benchmarks/results/gpu_check.json``. Numbers measured with ``--tiny`` are not measurements: the file says so.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .common import RESULTS_DIR, machine

SIZES = {  # steps timed per measurement (after warm-up steps that are not)
    "full": {"vae": 60, "lstm": 40, "updates": 1000, "decisions": 1000, "warmup": 5},
    "tiny": {"vae": 2, "lstm": 2, "updates": 20, "decisions": 20, "warmup": 1},
}


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(step, n: int, warmup: int, device) -> float:
    """Seconds per call of ``step`` over ``n`` calls, after ``warmup`` untimed ones."""
    for _ in range(warmup):
        step()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(n):
        step()
    _sync(device)
    return (time.perf_counter() - t0) / n


def vae_frames_per_s(cfg, device, steps: int, warmup: int) -> float:
    import torch

    from worldmodel import loading
    from worldmodel.models.vae import vae_loss

    torch.manual_seed(0)
    model = loading.build_vae(cfg.vae).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.vae.lr))
    batch = int(cfg.vae.batch_size)
    x = torch.randint(0, int(cfg.vae.num_classes), (batch, 64, 64), device=device)

    def step():
        logits, mu, logvar = model(x)
        loss, _, _ = vae_loss(logits, x, mu, logvar, float(cfg.vae.kl_weight), float(cfg.vae.free_bits))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return batch / _timed(step, steps, warmup, device)


def lstm_frames_per_s(cfg, device, steps: int, warmup: int) -> float:
    import torch

    from worldmodel import loading
    from worldmodel.train_rnn import masked_loss

    torch.manual_seed(0)
    model = loading.build_rnn(cfg.vae, cfg.rnn).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.rnn.lr))
    batch, length, latent = int(cfg.rnn.batch_size), int(cfg.rnn.seq_len), int(cfg.vae.latent_dim)
    z = torch.randn(batch, length, latent, device=device)
    a = torch.rand(batch, length, 2, device=device) * 2 - 1
    z_next = torch.randn(batch, length, latent, device=device)
    mask = torch.ones(batch, length, dtype=torch.bool, device=device)

    def step():
        out, _ = model(z, a)
        loss = masked_loss(model, out, z_next, mask)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()

    return batch * length / _timed(step, steps, warmup, device)


def ddpg_rates(cfg, device, updates: int, decisions: int, warmup: int) -> dict:
    """Updates per second at the agent's batch (drawn on the CPU, as training draws them) and decisions per second
    at batch 1, for the paper's observation [z, zhat, speed]."""
    import numpy as np
    import torch

    from worldmodel.models.ddpg import DDPG, DDPGConfig

    hp = DDPGConfig(batch_size=int(cfg.agent.ddpg.batch_size))
    obs_dim = 2 * int(cfg.vae.latent_dim) + 1
    agent = DDPG(obs_dim, 2, hp, seed=0, device=device)
    rng = np.random.default_rng(0)

    def batch():
        n = hp.batch_size
        return {
            "obs": torch.from_numpy(rng.normal(size=(n, obs_dim)).astype(np.float32)),
            "actions": torch.from_numpy(rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)),
            "rewards": torch.from_numpy(rng.normal(size=n).astype(np.float32)),
            "next_obs": torch.from_numpy(rng.normal(size=(n, obs_dim)).astype(np.float32)),
            "terminated": torch.zeros(n),
        }

    one = rng.normal(size=obs_dim).astype(np.float32)
    return {
        "updates_per_s": 1.0 / _timed(lambda: agent.update(batch()), updates, warmup, device),
        "decisions_per_s": 1.0 / _timed(lambda: agent.act(one, explore=False), decisions, warmup, device),
    }


def decisions_per_s(cfg, device, decisions: int, warmup: int) -> float:
    """Whole decisions per second at batch 1, as evaluation makes them: a frame through the VAE's mean and one LSTM
    step to the actor's action, on ``device`` (the fast path on the CPU, where it passes its self-test)."""
    import numpy as np
    import torch

    from worldmodel import loading
    from worldmodel.agent_obs import LearnedPolicy, WorldModelEncoder
    from worldmodel.models.ddpg import Actor

    torch.manual_seed(0)
    vae, rnn = loading.build_vae(cfg.vae).eval().to(device), loading.build_rnn(cfg.vae, cfg.rnn).eval().to(device)
    encoder = WorldModelEncoder(vae, rnn, use_speed=True)
    policy = LearnedPolicy("check", encoder, Actor(encoder.dim, 2).to(device))
    rng = np.random.default_rng(0)
    frames = rng.integers(0, int(cfg.vae.num_classes), (16, 64, 64), dtype=np.uint8)
    speed = np.array([10.0], np.float32)
    k = iter(range(10**9))
    return 1.0 / _timed(
        lambda: policy.act({"seg": frames[next(k) % 16], "speed": speed}, {}), decisions, warmup, device
    )


def smoke_pipeline(device: str) -> dict:
    """The smoke pipeline in a fresh folder, as a user would run it: its wall time and exit status."""
    with tempfile.TemporaryDirectory() as root:
        command = [
            sys.executable,
            "-m",
            "worldmodel.pipeline",
            "experiment=gpu_check",
            "scale=smoke",
            f"device={device}",
            f"paths.data_root={root}/data",
            f"paths.runs_root={root}/runs",
        ]
        t0 = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        return {
            "wall_s": round(time.perf_counter() - t0, 1),
            "returncode": done.returncode,
            "tail": (done.stdout + done.stderr)[-1500:] if done.returncode else "",
        }


def main(argv: list[str] | None = None) -> dict:
    import torch

    from worldmodel.common import resolve_device, set_threads
    from worldmodel.config import compose

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="the device checked against the CPU (default cuda)")
    parser.add_argument("--tiny", action="store_true", help="seconds-long sizes, to check that the script works")
    parser.add_argument("--no-pipeline", action="store_true", help="skip the smoke pipeline")
    parser.add_argument("--out", type=Path, default=None, help="folder for gpu_check.json ($OUT, else results/)")
    args = parser.parse_args(argv)

    device = resolve_device(args.device)
    cpu = torch.device("cpu")
    set_threads(os.cpu_count() or 1)  # the CPU side at its best on this machine
    size = SIZES["tiny" if args.tiny else "full"]
    cfg = compose("pipeline", ["scale=paper"])
    out: dict = {
        "machine": machine(),
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "tiny": bool(args.tiny),
        "batch": {"vae": int(cfg.vae.batch_size), "lstm": [int(cfg.rnn.batch_size), int(cfg.rnn.seq_len)]},
    }
    if not args.no_pipeline:
        out["smoke_pipeline"] = smoke_pipeline(args.device)
        print(f"smoke pipeline on {device}: {out['smoke_pipeline']}", flush=True)
    targets = [cpu] if device == cpu else [device, cpu]
    for name, measure in (
        ("vae_frames_per_s", lambda d: vae_frames_per_s(cfg, d, size["vae"], size["warmup"])),
        ("lstm_frames_per_s", lambda d: lstm_frames_per_s(cfg, d, size["lstm"], size["warmup"])),
        ("ddpg", lambda d: ddpg_rates(cfg, d, size["updates"], size["decisions"], size["warmup"])),
        ("decisions_per_s", lambda d: decisions_per_s(cfg, d, size["decisions"], size["warmup"])),
    ):
        out[name] = {str(d): measure(d) for d in targets}
        print(f"{name}: {out[name]}", flush=True)
    set_threads(2)  # the reference machine's cores, which the goal of twenty times is set against
    out["vae_frames_per_s"]["cpu_2_threads"] = vae_frames_per_s(cfg, cpu, size["vae"], size["warmup"])
    out["lstm_frames_per_s"]["cpu_2_threads"] = lstm_frames_per_s(cfg, cpu, size["lstm"], size["warmup"])
    set_threads(os.cpu_count() or 1)
    if device.type == "cuda":  # the batch a GPU run trains at (scale=paper_gpu)
        gpu_cfg = compose("pipeline", ["scale=paper_gpu"])
        batched = f"{device}_batch{int(gpu_cfg.vae.batch_size)}"
        out["vae_frames_per_s"][batched] = vae_frames_per_s(gpu_cfg, device, size["vae"], size["warmup"])
        out["lstm_frames_per_s"][batched] = lstm_frames_per_s(gpu_cfg, device, size["lstm"], size["warmup"])
    print(f"vae_frames_per_s: {out['vae_frames_per_s']}\nlstm_frames_per_s: {out['lstm_frames_per_s']}", flush=True)
    if device != cpu:
        best = {
            m: max(v for k, v in out[f"{m}_frames_per_s"].items() if not k.startswith("cpu")) for m in ("vae", "lstm")
        }
        out["speedup"] = {
            "vae_vs_2_cores": best["vae"] / out["vae_frames_per_s"]["cpu_2_threads"],
            "lstm_vs_2_cores": best["lstm"] / out["lstm_frames_per_s"]["cpu_2_threads"],
            "vae": out["vae_frames_per_s"][str(device)] / out["vae_frames_per_s"]["cpu"],
            "lstm": out["lstm_frames_per_s"][str(device)] / out["lstm_frames_per_s"]["cpu"],
            "ddpg_updates": out["ddpg"][str(device)]["updates_per_s"] / out["ddpg"]["cpu"]["updates_per_s"],
            "decisions": out["ddpg"][str(device)]["decisions_per_s"] / out["ddpg"]["cpu"]["decisions_per_s"],
            "whole_decisions": out["decisions_per_s"][str(device)] / out["decisions_per_s"]["cpu"],
        }
    folder = args.out or (Path(os.environ["OUT"]) if os.environ.get("OUT") else RESULTS_DIR)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "gpu_check.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {folder / 'gpu_check.json'}")
    return out


if __name__ == "__main__":
    main()
