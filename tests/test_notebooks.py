"""The example notebooks run clean, top to bottom, in a fresh kernel (as CI runs them)."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "examples" / "notebooks").glob("*.ipynb"))
WIDGET = "application/vnd.jupyter.widget-view+json"


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs_clean(path, tmp_path):
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(notebook, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    errors = [o for o in outputs if o.output_type == "error"]
    assert not errors, errors
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "complete [" in text and "converged          = True" in text, text[-3000:]
    # Progress is a notebook widget, and nothing printed terminal control codes.
    assert any(WIDGET in o.get("data", {}) for o in outputs if o.output_type == "display_data")
    assert "\x1b[" not in text
    assert any("image/png" in o.get("data", {}) for o in outputs if o.output_type == "display_data")
