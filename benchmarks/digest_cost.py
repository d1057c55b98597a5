"""What checking a checkpoint's digest adds to loading it, in a fresh process (benchmarks/RESULTS.md).

    python -m benchmarks.digest_cost load  [CHECKPOINT]   # reading it alone, as a stage loaded a model before
    python -m benchmarks.digest_cost check [CHECKPOINT]   # the file's SHA-256 first, as artifacts.check_output does

The default checkpoint is the paper-scale VAE's (runs/headline/vae/best.pt, 56 MB), the largest model a stage loads
whole; an agent's last.pt with its replay memory is about as large.
"""

from __future__ import annotations

import sys

from worldmodel.checkpoints import read_checkpoint
from worldmodel.common import file_sha256


def main(argv: list[str]) -> None:
    mode, path = argv[0], (argv[1] if len(argv) > 1 else "runs/headline/vae/best.pt")
    if mode == "check":
        file_sha256(path)
    elif mode != "load":
        raise SystemExit("usage: python -m benchmarks.digest_cost load|check [CHECKPOINT]")
    read_checkpoint(path)


if __name__ == "__main__":
    main(sys.argv[1:])
