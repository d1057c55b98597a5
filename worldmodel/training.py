"""What every training stage shares: checkpoints with everything needed to resume, TensorBoard, and a
clean stop on SIGINT/SIGTERM.

A checkpoint holds model, optimiser, epoch, position within the epoch, global step, RNG states and the
stage's own extras. ``last.pt`` is rewritten atomically at every save; ``best.pt`` when validation improves,
and before ``last.pt``, so a kill between the two never leaves ``best.pt`` behind what ``last.pt`` records.
Resuming restores all of it, and TensorBoard keeps counting from the saved step (ctallec/world-models
restored its scheduler from the wrong state dict; resume is tested here).
"""
from __future__ import annotations

import signal
from pathlib import Path

from .common import StageError, atomic_torch_save, load_checkpoint, rng_state, set_rng_state


class GracefulStop:
    """Turns SIGINT/SIGTERM into a flag the training loop checks, so it can checkpoint and exit cleanly."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def _handler(self, signum, frame):
        if self.requested:  # a second Ctrl-C means "now"
            raise KeyboardInterrupt
        self.requested = True
        print(f"\n[stop] {signal.Signals(signum).name} received: saving a checkpoint, then exiting.")

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[sig] = signal.signal(sig, self._handler)
            except ValueError:  # not the main thread (e.g. inside a notebook kernel thread)
                pass
        return self

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        return False


class Checkpoints:
    """``runs/NAME/<stage>/{last,best}.pt`` for one stage."""

    def __init__(self, directory: Path, stage_cmd: str, cfg):
        self.dir = Path(directory)
        self.last = self.dir / "last.pt"
        self.best = self.dir / "best.pt"
        self._stage_cmd = stage_cmd
        self._cfg = cfg

    def save(self, state: dict, best: bool = False) -> None:
        state = {**state, "rng": rng_state()}
        # best.pt first: a process killed between the two writes then resumes from the previous last.pt and
        # redoes the improvement. The other order would leave last.pt recording a best that best.pt lacks.
        if best:
            atomic_torch_save(state, self.best)
        atomic_torch_save(state, self.last)

    def resume_state(self, resume: bool) -> dict | None:
        """The state to continue from, or None for a fresh start; refuses to overwrite without resume."""
        # A process killed inside a save leaves its temporary file (possibly hundreds of MB with a replay buffer);
        # only this run writes here, so whatever is left over belongs to a dead writer.
        for stale in self.dir.glob(".*.pt.*.tmp"):
            stale.unlink(missing_ok=True)
        if not self.last.exists():
            return None
        if not resume:
            raise StageError(
                f"{self.last} exists. Pass resume=true to continue that run, or delete {self.dir} to start over.")
        state = load_checkpoint(self.last, "checkpoint", self._stage_cmd, self._cfg)
        set_rng_state(state["rng"])
        return state


def tensorboard(directory: Path, purge_step: int | None = None):
    from torch.utils.tensorboard import SummaryWriter

    # purge_step drops events logged after the checkpoint we resume from, so curves do not zig-zag.
    return SummaryWriter(log_dir=str(directory), purge_step=purge_step)
