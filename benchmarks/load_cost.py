"""What reading checkpoints safely costs (benchmarks/RESULTS.md, "Reading checkpoints safely").

    python -m benchmarks.load_cost [--vae runs/NAME/vae/best.pt] [--replay 100000] [-n 7]

Times, in one process and in alternating pairs, the full unpickler a checkpoint was read with before
(``torch.load(weights_only=False)``) against the project's reader (``worldmodel.checkpoints.read_checkpoint``,
torch's weights-only unpickler with numpy's arrays allowed), on two files: a VAE's checkpoint (the paper's VAE,
56 MB, the largest model a stage loads whole) and an agent's checkpoint holding a full replay memory of ``--replay``
transitions of the paper's DDPG observation (2 x 128 + 1 floats), written the way a stage writes it. The full
unpickler runs whatever a file names: point ``--vae`` at a checkpoint you wrote.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from worldmodel.checkpoints import read_checkpoint
from worldmodel.common import atomic_torch_save, rng_state
from worldmodel.models.ddpg import ReplayBuffer


def replay_checkpoint(path: Path, transitions: int, obs_dim: int = 2 * 128 + 1) -> Path:
    buffer = ReplayBuffer(transitions, obs_dim, 2)
    for name in buffer.FIELDS:
        getattr(buffer, name)[:] = torch.rand(getattr(buffer, name).shape).numpy()
    buffer.pos, buffer.size = 0, transitions
    atomic_torch_save({"agent": {"buffer": buffer.state_dict()}, "rng": rng_state(), "step": transitions}, path)
    return path


def seconds(load, path: Path) -> float:
    t0 = time.perf_counter()
    load(path)
    return time.perf_counter() - t0


def full(path: Path):
    return torch.load(path, map_location="cpu", weights_only=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vae", type=Path, default=Path("runs/headline/vae/best.pt"))
    parser.add_argument("--replay", type=int, default=100_000, help="transitions in the replay memory")
    parser.add_argument("-n", type=int, default=7, help="pairs counted, after one pair not counted")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        files = {"VAE": args.vae, "replay": replay_checkpoint(Path(tmp) / "last.pt", args.replay)}
        for what, path in files.items():
            seconds(full, path), seconds(read_checkpoint, path)  # warm the file cache
            pairs = [(seconds(read_checkpoint, path), seconds(full, path)) for _ in range(args.n)]
            safe, before = (statistics.median(p[k] for p in pairs) for k in (0, 1))
            ratios = [s / f for s, f in pairs]
            print(
                f"{what} ({path.stat().st_size / 2**20:.0f} MiB): safe {safe:.3f} s, full {before:.3f} s "
                f"(medians of {args.n}); safe/full {statistics.median(ratios):.3f} "
                f"(pairs {min(ratios):.3f}-{max(ratios):.3f})"
            )


if __name__ == "__main__":
    main()
