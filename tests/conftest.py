"""Shared fixtures: real Hydra configs composed with the compose API into a temporary experiment root."""

from __future__ import annotations

import gc
import os
import shutil

import pytest

# Test banks from test-only seeds, and a real sealed seed an error (worldmodel/banks.py); set before any import of
# worldmodel, and inherited by every stage a test runs in a subprocess
os.environ["WORLDMODEL_TEST_SUITE"] = "1"

from worldmodel.config import compose  # noqa: E402

# Tests share 2 cores with nothing else; one torch thread keeps them predictable.
os.environ.setdefault("OMP_NUM_THREADS", "1")


# The files that take longest, longest first. `make test` runs each file whole on one of two workers
# (--dist loadfile) in collection order: a long file collected last (alphabetically, test_pipeline.py and
# test_resume.py) would run alone at the end while the other worker idles. Taking them first lets the short files
# fill in around them.
SLOWEST_FIRST = (
    "test_pipeline.py",
    "test_resume.py",
    "test_interrupt.py",
    "test_published.py",
    "test_chae.py",
    "test_device.py",
    "test_launchers.py",
    "test_safe_loading.py",
    "test_planner.py",
    "test_camera_views.py",
    "test_kim.py",
)


def pytest_configure(config):
    # pytest-xdist reorders the files by their number of tests unless told not to, which undoes SLOWEST_FIRST
    if getattr(config.option, "loadscopereorder", None):
        config.option.loadscopereorder = False


def pytest_collection_finish(session):
    # Every test module is imported by now, and with them torch, Hydra and the project: objects that live until the
    # end. Frozen, Python's full garbage collections no longer walk them. The tests then allocate millions of
    # short-lived containers (configs, rows, checkpoints' dicts); collecting the youngest every 10,000 allocations
    # instead of every 700, and the oldest ten times less often, took the collector from 20 s of the two workers'
    # CPU time to 8 s, and the run's peak memory did not rise (benchmarks/RESULTS.md). Garbage is still collected.
    gc.freeze()
    gc.set_threshold(10_000, 10, 100)


def pytest_collection_modifyitems(config, items):
    rank = {name: k for k, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file keeps its own order


@pytest.fixture
def stage_cfg(tmp_path):
    """stage_cfg("collect", "scale=smoke", ...) -> the real config rooted at tmp_path."""

    def make(stage: str, *overrides: str, root=None):
        root = root or tmp_path
        return compose(
            stage,
            [
                f"paths.data_root={root}/data",
                f"paths.runs_root={root}/runs",
                f"paths.ledger={root}/ledger.csv",  # never the repository's ledger
                "experiment=t",
                "scale=smoke",
                "threads=1",
                *overrides,
            ],
        )

    return make


@pytest.fixture(scope="session")
def smoke_builds(tmp_path_factory):
    """smoke_builds("rollouts" | "vae" | "rnn") -> a root holding a smoke-scale experiment ``t`` built by the real
    stages up to that stage, once per test session. Read-only: tests that change it take ``experiment_copy``."""
    from worldmodel import collect, train_rnn, train_vae

    order = {"rollouts": collect.run, "vae": train_vae.run, "rnn": train_rnn.run}
    stage_of = {"rollouts": "collect", "vae": "train_vae", "rnn": "train_rnn"}
    built: dict = {}

    def build(level: str):
        if level not in built:
            root = tmp_path_factory.mktemp(f"built-{level}")
            names = list(order)
            previous = names[names.index(level) - 1] if names.index(level) else None
            if previous:
                shutil.copytree(build(previous), root, dirs_exist_ok=True)
            order[level](
                compose(
                    stage_of[level],
                    [
                        f"paths.data_root={root}/data",
                        f"paths.runs_root={root}/runs",
                        "experiment=t",
                        "scale=smoke",
                        "threads=1",
                    ],
                )
            )
            built[level] = root
        return built[level]

    return build


@pytest.fixture
def experiment_copy(smoke_builds, tmp_path):
    """experiment_copy("vae") -> tmp_path holding a private copy of the session's smoke build up to that stage."""

    def make(level: str):
        shutil.copytree(smoke_builds(level), tmp_path, dirs_exist_ok=True)
        return tmp_path

    return make


@pytest.fixture
def dead_pid():
    """The pid of a process that has just exited: what a killed writer leaves in its temporary file's name."""
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid
