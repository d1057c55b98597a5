"""A stage's console holds its log lines and its progress bars, and nothing else, when it runs its work in worker
processes: no pybullet build-time banner from each worker that starts the simulator, and no warnings of
multiprocessing's resource tracker about semaphores the workers left behind (tqdm makes one in each worker).

Each stage runs as a user runs it, ``python -m worldmodel.STAGE`` in a subprocess with two workers, and its stdout
and stderr are read together, as a terminal shows them.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LOG_LINE = re.compile(r"^\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+\]\[[\w.]+\]\[INFO\] - ")
PROGRESS_BAR = re.compile(r"^[\w ]+: +\d+%\|")  # tqdm: "collect:  50%|█████     | 2/4 [...]"


def console(tmp_path: Path, stage: str, *overrides: str) -> list[str]:
    """The non-empty lines a terminal would show for the stage, progress bar updates each on a line of its own."""
    cmd = [
        sys.executable,
        "-m",
        f"worldmodel.{stage}",
        f"paths.data_root={tmp_path}/data",
        f"paths.runs_root={tmp_path}/runs",
        f"paths.ledger={tmp_path}/ledger.csv",
        "experiment=t",
        "scale=smoke",
        "threads=1",
        *overrides,
    ]
    result = subprocess.run(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=240)
    assert result.returncode == 0, result.stdout
    return [line for line in re.split(r"[\r\n]", result.stdout) if line.strip()]


def stray(lines: list[str]) -> list[str]:
    return [line for line in lines if not (LOG_LINE.match(line) or PROGRESS_BAR.match(line))]


def test_collection_workers_print_no_pybullet_banner(tmp_path):
    """Two workers, one shard each, both with the camera on: each imports pybullet."""
    lines = console(tmp_path, "collect", "collect.num_workers=2")
    assert not [line for line in lines if "pybullet build time" in line]
    assert stray(lines) == []
    assert any("[collect]" in line and "4 episodes" in line for line in lines)


def test_evaluation_workers_leave_no_semaphores_behind(tmp_path):
    """Two workers, four chunks of one scenario: every worker runs the per-scenario loop, which makes tqdm's lock."""
    tiny = ["evaluate.ttcs=[1.0]", "evaluate.speeds=[10.0]", "evaluate.hazards=[pedestrian]", "evaluate.per_cell=4"]
    lines = console(tmp_path, "evaluate", *tiny, "evaluate.policies=[braking]", "evaluate.num_workers=2")
    assert not [line for line in lines if "resource_tracker" in line or "leaked" in line]
    assert stray(lines) == []
    assert any("[eval] 4 scenarios x 1 policies" in line for line in lines)
