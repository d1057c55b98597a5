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
    assert any("[eval porav] 4 scenarios x 1 policies" in line for line in lines)


def test_a_root_that_cannot_be_written_is_one_sentence_and_exit_2(tmp_path):
    """``paths.runs_root`` under a file (as a read-only folder, it cannot be written): one line naming the key, the
    path and the fix, exit 2, no traceback, and nothing written under the other root."""
    (tmp_path / "file").write_text("")
    cmd = [sys.executable, "-m", "worldmodel.collect", f"paths.runs_root={tmp_path}/file/runs"]
    cmd += [f"paths.data_root={tmp_path}/data", "experiment=t", "scale=smoke"]
    result = subprocess.run(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1, result.stdout
    assert (
        lines[0].startswith(f"error: paths.runs_root={tmp_path}/file/runs cannot be written") and "a file" in lines[0]
    )
    assert not (tmp_path / "data").exists()


def test_a_key_named_at_its_old_place_is_one_sentence_with_its_new_one_and_exit_2(tmp_path):
    """DDPG's keys moved into ``agent.ddpg``: ``agent.n_step=3`` on the command line stops before Hydra reads it,
    with the override to write instead."""
    cmd = [sys.executable, "-m", "worldmodel.train_agent", f"paths.runs_root={tmp_path}/runs", "agent.n_step=3"]
    result = subprocess.run(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    assert result.returncode == 2 and lines == [
        "error: agent.n_step is now agent.ddpg.n_step: write agent.ddpg.n_step=3"
    ]
    assert not (tmp_path / "runs").exists()


def test_a_full_or_read_only_disk_inside_a_stage_is_one_sentence():
    """What a stage says when the disk stops it: the file, why, and what to do (a full disk loses nothing finished)."""
    import errno

    from worldmodel.config.entry import disk_error_sentence

    full = disk_error_sentence(OSError(errno.ENOSPC, "No space left on device", "runs/t/vae/last.pt"), "train_vae")
    assert "runs/t/vae/last.pt" in full and "full" in full and "resume=true" in full
    read_only = disk_error_sentence(OSError(errno.EROFS, "Read-only file system", "data/t/x.h5"), "collect")
    assert "data/t/x.h5" in read_only and "Read-only file system" in read_only and "paths.data_root" in read_only
    assert disk_error_sentence(OSError(errno.ENOENT, "No such file or directory", "x"), "collect") is None
