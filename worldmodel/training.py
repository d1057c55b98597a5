"""What every training stage shares: one run directory through its life (refuse or resume, record its inputs,
checkpoint, log to TensorBoard, stop cleanly on SIGINT/SIGTERM, mark it finished).

A checkpoint holds model, optimiser, epoch, position within the epoch, global step, RNG states, the run's
provenance (artifacts.py) and the stage's own extras. ``last.pt`` is rewritten atomically at every save;
``best.pt`` when validation improves, and before ``last.pt``, so a kill between the two never leaves
``best.pt`` behind what ``last.pt`` records. Resuming restores all of it, and TensorBoard keeps counting from
the saved step (ctallec/world-models restored its scheduler from the wrong state dict; resume is tested here).
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import time
from pathlib import Path

import numpy as np

from . import artifacts
from .common import (
    StageError,
    atomic_torch_save,
    atomic_write_text,
    clean_temporaries,
    load_checkpoint,
    rng_state,
    set_rng_state,
    stage_command,
    writer_lock,
)

log = logging.getLogger(__name__)


class GracefulStop:
    """Turns SIGINT/SIGTERM into a flag the training loop checks, so it can checkpoint and exit cleanly."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def _handler(self, signum, frame):
        if self.requested:  # a second Ctrl-C means "now"
            raise KeyboardInterrupt
        self.requested = True
        log.warning("%s received: saving a checkpoint, then exiting.", signal.Signals(signum).name)

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


def tensorboard(directory: Path, purge_step: int | None = None):
    from torch.utils.tensorboard import SummaryWriter

    if purge_step is not None:
        wait_for_a_later_second(directory)
    # purge_step drops events logged after the checkpoint we resume from, so curves do not zig-zag.
    return SummaryWriter(log_dir=str(directory), purge_step=purge_step)


def wait_for_a_later_second(directory: Path) -> None:
    """TensorBoard reads a run's event files in the order of their names, which begin with the second the file was
    opened in (then host, process id and a counter, compared as text). A resumed run's file that shared that second
    with an earlier one could be read first, and its purge would then drop the earlier points. Waits (at most a
    second, and only when resuming that fast) until the clock has passed every existing file's second."""
    stamps = []
    for path in Path(directory).glob("events.out.tfevents.*"):
        field = path.name.split(".")[3]
        if field.isdigit():
            stamps.append(int(field))
    while stamps and int(time.time()) <= max(stamps):
        time.sleep(0.05)


class TrainingRun:
    """The skeleton of a training stage around its own loop::

        with TrainingRun(cfg, "train_vae", out, artifacts.provenance(cfg, "vae")) as run:
            if run.state is not None: ...restore model, optimiser and counters from run.state...
            while ...:
                ...train; run.writer.add_scalar(...)...
                if run.stop.requested:
                    run.save(state)
                    return run.stopped(step)
                run.save(state, best=improved)
            return run.finish(metrics)

    On entry it refuses to overwrite a finished run without ``resume=true``, refuses to resume a run whose
    recorded inputs (dataset, VAE, LSTM) differ from the current ones (unless ``allow_stale=true``), removes the
    temporary file of a save that a kill interrupted, loads ``last.pt`` when resuming, records the run's inputs
    in ``provenance.json`` and opens TensorBoard and the signal handler.
    """

    MARKER = "metrics.json"

    def __init__(self, cfg, command: str, directory: Path, record: dict, name: str | None = None):
        self.cfg, self.command, self.dir, self.record = cfg, command, Path(directory), record
        self.name = name or command.removeprefix("train_")
        self.last, self.best = self.dir / "last.pt", self.dir / "best.pt"
        self.marker = self.dir / self.MARKER
        self.state: dict | None = None
        self.stop = GracefulStop()
        self.writer = None
        self._side_writers: list = []

    # ------------------------------------------------------------------ life cycle

    @classmethod
    def for_agent(cls, cfg, agent_id) -> TrainingRun:
        """``train_agent``'s run of the agent ``agent_id``: its folder, its provenance and its name."""
        return cls(cfg, "train_agent", agent_id.dir(cfg), artifacts.provenance(cfg, "agent"), name=agent_id.policy)

    def __enter__(self) -> TrainingRun:
        self._held = contextlib.ExitStack()
        self._held.enter_context(writer_lock(self.dir, f"the {self.name} run"))
        try:
            return self._enter()
        except BaseException:
            self._held.close()
            raise

    def _enter(self) -> TrainingRun:
        resume = bool(self.cfg.resume)
        finished = self.marker.exists()
        if finished and not resume:
            raise StageError(
                f"{self.dir} holds a finished run. Pass resume=true to keep it, or delete {self.dir} to retrain."
            )
        if finished:
            self._check_outputs()
        # Only this run writes here, so a temporary file belongs to a writer that was killed inside a save
        # (possibly hundreds of MB with a replay buffer).
        if self.dir.exists():
            clean_temporaries(self.dir)
        if self.last.exists():
            if not resume:
                raise StageError(
                    f"{self.last} exists. Pass resume=true to continue that run, or delete {self.dir} to start over."
                )
            self._check_resumed_inputs()
            self.state = load_checkpoint(self.last, "checkpoint", self.command, self.cfg)
            set_rng_state(self.state["rng"])
        self.dir.mkdir(parents=True, exist_ok=True)
        # a finished run resumed may train on (more epochs): its checkpoints are recorded again when it finishes
        artifacts.write_provenance(self.dir, self.record)
        # "log_step": the x-axis of a stage whose curves count episodes rather than steps
        logged = self.state.get("log_step", self.state["step"]) if self.state else None
        self.writer = tensorboard(self.dir, purge_step=logged + 1 if self.state else None)
        self.stop.__enter__()
        return self

    def __exit__(self, *exc):
        self.stop.__exit__(*exc)
        for writer in [self.writer, *self._side_writers]:
            if writer is not None:
                writer.close()
        self._held.close()
        return False

    def side_writer(self, name: str, purge_step: int | None = None):
        """TensorBoard curves on an x-axis of their own (pre-training minibatches), in ``<run>/<name>/``: the main
        writer's purge on resume, which counts environment steps, leaves them alone. ``purge_step``: where a resumed
        run's own count starts again."""
        writer = tensorboard(self.dir / name, purge_step=purge_step)
        self._side_writers.append(writer)
        return writer

    def _check_outputs(self) -> None:
        """A finished run resumed (``resume=true``) must still hold the checkpoints it wrote: its metrics describe
        them, and a resumed run would record whatever is there now as its own."""
        changed = artifacts.changed_outputs(self.dir)
        if not changed:
            return
        message = (
            f"{self.dir} holds a finished run whose checkpoints changed since ({'; '.join(changed)}). Restore "
            f"them, or delete {self.dir} and rerun `{stage_command(self.command, self.cfg)}` to retrain; "
            "allow_stale=true keeps them anyway."
        )
        artifacts.refuse_unless_allowed_stale(self.cfg, message)

    def _check_resumed_inputs(self) -> None:
        recorded = artifacts.read_provenance(self.dir)
        if recorded is None:
            return
        changed = [
            r
            for r in artifacts.differences(
                recorded, self.record, artifacts.legacy_identities(artifacts.dataset_manifests(self.cfg))
            )
            if r != "its config changed"
        ]
        if not changed:
            return
        message = (
            f"{self.dir} was started on other inputs ({'; '.join(changed)}), so resuming it would mix "
            f"them. Delete {self.dir} and rerun `{stage_command(self.command, self.cfg)}`, or run the "
            "pipeline, which sets stale runs aside and rebuilds them; allow_stale=true resumes anyway."
        )
        artifacts.refuse_unless_allowed_stale(self.cfg, message)

    # ------------------------------------------------------------------ during training
    def save(self, state: dict, best: bool = False) -> None:
        state = {**state, "provenance": self.record, "rng": rng_state()}
        # best.pt first: a process killed between the two writes then resumes from the previous last.pt and
        # redoes the improvement. The other order would leave last.pt recording a best that best.pt lacks.
        if best:
            atomic_torch_save(state, self.best)
        atomic_torch_save(state, self.last)

    def restore(self, model, optimizer) -> tuple[int, int, int, float]:
        """For the epoch-based stages: load model and optimiser from the checkpoint being resumed and return
        ``(epoch, batch_in_epoch, step, best_val)``; a fresh run starts from ``(0, 0, 0, inf)``."""
        if self.state is None:
            return 0, 0, 0, float("inf")
        s = self.state
        model.load_state_dict(s["model"])
        optimizer.load_state_dict(s["optimizer"])
        self.resumed(f"epoch {s['epoch']}, step {s['step']}")
        return s["epoch"], s["batch_in_epoch"], s["step"], s["best_val"]

    def save_epochs(self, model, optimizer, counters: tuple[int, int, int, float], best: bool = False, **extras):
        """``save`` for the epoch-based stages: model, optimiser and the counters ``restore`` returns."""
        epoch, batch_in_epoch, step, best_val = counters
        state = {
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "epoch": epoch,
            "batch_in_epoch": batch_in_epoch,
            "step": step,
            "best_val": best_val,
        }
        self.save({**state, **extras}, best=best)

    def restore_random_state(self) -> None:
        """Put the process-wide generators back as the checkpoint left them (a fresh run: leave them). For a stage
        that builds networks or views after entering, which draw from them: call it once they are built."""
        if self.state is not None:
            set_rng_state(self.state["rng"])

    def resumed(self, where: str) -> None:
        log.info("[%s] resuming from %s: %s", self.name, self.last, where)

    def stopped(self, step: int) -> dict:
        log.info("[%s] stopped at step %d; resume with resume=true", self.name, step)
        return {"stopped": True, "step": step}

    def finish(self, metrics: dict) -> dict:
        """Record the digests of the run's checkpoints, then write the completion marker: the run is done."""
        artifacts.write_provenance(self.dir, {**self.record, "outputs": artifacts.output_digests(self.dir)})
        atomic_write_text(self.marker, json.dumps(metrics, indent=2))
        return metrics


class EpisodeInProgress:
    """The training episode under way, kept so that a checkpoint taken inside it resumes exactly.

    The simulator is deterministic given how an episode started and the actions taken since, so a checkpoint
    keeps only those: ``resume`` starts the episode again and replays the actions, which rebuilds the simulator,
    any recurrent view of it (the world model's LSTM state, a frame history) and the observation as they were.
    The learner's own state (its random generators, replay memory, n-step window) travels in the checkpoint beside
    it. Replaying draws from no random generator, so restoring them before or after makes no difference.
    """

    def __init__(self, env):
        self.env = env
        self.start: dict = {}
        self.actions: list[np.ndarray] = []
        self.obs = None

    def reset(self, **start):
        """``env.reset(**start)``, remembered as this episode's start."""
        self.start, self.actions = dict(start), []
        self.obs, info = self.env.reset(**start)
        return self.obs, info

    def step(self, action):
        out = self.env.step(action)
        self.actions.append(np.array(action, copy=True))  # its own dtype: the replay must feed the same bits
        self.obs = out[0]
        return out

    def __len__(self) -> int:
        return len(self.actions)

    def state_dict(self) -> dict:
        return {"start": self.start, "actions": list(self.actions), "obs": self.obs}

    def resume(self, state: dict, where: Path):
        """Start the saved episode again and replay its actions; returns ``(obs, info)`` at the saved step."""
        obs, info = self.reset(**state["start"])
        for k, action in enumerate(state["actions"]):
            obs, _, terminated, truncated, info = self.step(action)
            if (terminated or truncated) and k + 1 < len(state["actions"]):
                raise StageError(
                    f"the episode in progress in {where} ended after {k + 1} of its {len(state['actions'])} replayed "
                    "actions: this simulator does not replay it as the one that saved it did (another pybullet or "
                    "numpy build?). Resume on the machine that wrote it, or delete the run folder to start over."
                )
        if not np.array_equal(obs, state["obs"]):
            log.warning(
                "the episode in progress in %s replayed to a different observation (another torch build or thread "
                "count?): the run goes on from the replayed one, no longer bit-identical to an uninterrupted run",
                where,
            )
        return obs, info
