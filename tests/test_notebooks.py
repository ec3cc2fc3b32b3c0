"""The notebooks in notebooks/ run top to bottom with their small settings (NOTEBOOK_SMALL=1), as a user's Jupyter
would run them: each in its own kernel, from its own folder. A cell that raises fails the test with its traceback."""

from __future__ import annotations

import os

import pytest

from tests.conftest import ROOT

nbformat = pytest.importorskip("nbformat", reason="the dev extra's nbformat, nbclient and ipykernel run the notebooks")
nbclient = pytest.importorskip("nbclient", reason="the dev extra's nbformat, nbclient and ipykernel run the notebooks")

NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


def test_there_are_notebooks():
    assert {path.name for path in NOTEBOOKS} >= {"image_field.ipynb", "splats_lego.ipynb"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_is_committed_clean(path):
    """No outputs in the repository (a diff shows the code, not images), and a settings cell tagged for papermill."""
    notebook = nbformat.read(path, as_version=4)
    nbformat.validate(notebook)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert all(not cell.outputs and cell.execution_count is None for cell in code), f"{path.name}: clear its outputs before committing"
    assert "parameters" in code[0].metadata.get("tags", []), f"{path.name}: its first code cell holds the settings, tagged parameters"
    assert "NOTEBOOK_SMALL" in code[0].source


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_runs_small(path, tmp_path, monkeypatch):
    monkeypatch.setenv("NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("NOTEBOOK_OUTPUT_DIR", str(tmp_path))
    # the kernel starts in notebooks/: it imports the package of this tree, whatever a relative PYTHONPATH meant here
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}})
    client.execute()  # CellExecutionError: the cell, and its traceback
    pictures = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.get("outputs", [])
                if "image/png" in output.get("data", {})]
    assert pictures, f"{path.name} showed no figure"
