"""Shared fixtures: real Hydra configs composed with the compose API into a temporary experiment root."""
from __future__ import annotations

import os

import pytest

from worldmodel.common import compose

# Tests share 2 cores with nothing else; one torch thread keeps them predictable.
os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture
def stage_cfg(tmp_path):
    """stage_cfg("collect", "scale=smoke", ...) -> the real config rooted at tmp_path."""

    def make(stage: str, *overrides: str, root=None):
        root = root or tmp_path
        return compose(stage, [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t",
                               "scale=smoke", "threads=1", *overrides])

    return make
