"""notebooks/decode_predictions.ipynb: committed clean, and runs end to end on real smoke-scale artifacts.

The notebook is executed in memory (a copy) with nbclient in a real kernel; the file on disk is never written.
"""

from __future__ import annotations

import copy
import hashlib
from pathlib import Path

import pytest

from worldmodel.common import PROJECT_ROOT

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOK_DIR = PROJECT_ROOT / "notebooks"
NOTEBOOK = NOTEBOOK_DIR / "decode_predictions.ipynb"


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_committed_notebook_has_no_outputs():
    """Fails if someone commits the notebook with outputs or execution counts."""
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code, "the notebook has no code cells"
    dirty = [
        i
        for i, c in enumerate(nb.cells)
        if c.cell_type == "code" and (c.get("outputs") or c.get("execution_count") is not None)
    ]
    assert not dirty, (
        f"cells {dirty} of {NOTEBOOK} hold outputs or execution counts: clear them before committing "
        "(Jupyter: Edit > Clear Outputs of All Cells, then save)"
    )
    tagged = [c for c in code if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1 and "HORIZON" in tagged[0].source and "WM_EXPERIMENT" in tagged[0].source


@pytest.fixture(scope="module")
def smoke_artifacts(smoke_builds):
    """A real smoke-scale experiment ``t``: rollouts, VAE, latents and LSTM, built by the stages themselves
    (shared with the other test modules; the notebook only reads it)."""
    return smoke_builds("rnn")


@pytest.fixture(scope="module")
def executed(smoke_artifacts):
    """The notebook run in memory from notebooks/ against the smoke experiment; returns (notebook, digest before)."""
    before = _digest(NOTEBOOK)
    nb = copy.deepcopy(nbformat.read(NOTEBOOK, as_version=4))
    env = {
        "WM_EXPERIMENT": "t",
        "WM_DATA_ROOT": str(smoke_artifacts / "data"),
        "WM_RUNS_ROOT": str(smoke_artifacts / "runs"),
        "WM_SCALE": "smoke",
        "OMP_NUM_THREADS": "1",
    }
    with pytest.MonkeyPatch.context() as mp:
        for key, value in env.items():  # the kernel inherits this process's environment
            mp.setenv(key, value)
        mp.delenv("MPLBACKEND", raising=False)  # an Agg backend would silently swallow the figures
        client = nbclient.NotebookClient(
            nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK_DIR)}}
        )
        client.execute()  # raises CellExecutionError, with the cell's traceback, on any error
    return nb, before


def _outputs(nb):
    return [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]


@pytest.mark.slow
def test_notebook_runs_and_draws_figures(executed):
    nb, _ = executed
    outputs = _outputs(nb)
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if o.output_type == "display_data" and "image/png" in o.get("data", {})]
    assert len(images) >= 3, f"expected the three figures, got {len(images)} images"
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "loaded VAE" in text and "loaded LSTM" in text
    assert "notebook ran in" in text


@pytest.mark.slow
def test_executing_leaves_the_committed_file_untouched(executed):
    nb, before = executed
    assert _outputs(nb), "the in-memory copy should hold the outputs"
    assert _digest(NOTEBOOK) == before
    on_disk = nbformat.read(NOTEBOOK, as_version=4)
    assert all(
        not c.get("outputs") and c.get("execution_count") is None for c in on_disk.cells if c.cell_type == "code"
    )
