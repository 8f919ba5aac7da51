"""notebooks/explore.ipynb runs top to bottom (nbclient) on the tiny config, so it cannot rot; and
its outputs stay cleared in git."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK = REPO / "notebooks" / "explore.ipynb"
CELL_TIMEOUT_S = 900  # the first cell trains configs/tiny.yaml


def test_notebook_outputs_are_cleared():
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    dirty = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and c.get("outputs")]
    counts = [i for i, c in enumerate(nb.cells) if c.get("execution_count") is not None]
    assert not dirty and not counts, f"clear the outputs of cells {sorted(set(dirty + counts))}"


@pytest.mark.slow
def test_notebook_executes(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("EVOJAX_NOTEBOOK_DIR", str(tmp_path / "run"))
    monkeypatch.delenv("EVOJAX_RUN", raising=False)
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK.parent)}},
    )
    client.execute()  # raises CellExecutionError naming the failing cell
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    figures = tmp_path / "run" / "notebook_figures"
    for name in ("fig4_basis.png", "fig5_costs.png", "tradeoff.png", "fig8.png", "catch.gif"):
        assert (figures / name).is_file(), name
