"""The notebooks run top to bottom, headless, on a tiny multirun and one of its runs."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

from conftest import REPO, run_module

pytestmark = pytest.mark.slow

NOTEBOOKS = REPO / "notebooks"


@pytest.fixture(scope="module")
def tiny_multirun(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two tiny trainings (w_s = 0 and 100): a multirun, and each job is a run directory."""
    tmp = tmp_path_factory.mktemp("notebooks")
    sweep = tmp / "sweep"
    run_module(
        "mfg_lightning.train",
        "-m",
        "debug=tiny",
        "model.loss.w_s=0,100",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp,
    )
    return sweep


def _execute(name: str, cwd: Path) -> nbformat.NotebookNode:
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    # the committed notebooks carry no outputs
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), name
    client = NotebookClient(
        nb, timeout=180, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}
    )
    client.execute()  # raises CellExecutionError on the first failing cell
    return nb


def _outputs(nb: nbformat.NotebookNode) -> tuple[str, int]:
    """All printed text and the number of PNG images the notebook displayed."""
    text, images = [], 0
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            assert out.get("output_type") != "error", out
            text.append(out.get("text", ""))
            data = out.get("data", {})
            text.append(data.get("text/markdown", ""))
            images += "image/png" in data
    return "\n".join(text), images


@pytest.mark.parametrize(
    "name,expected_text,min_images",
    [
        ("training_curves", "scalar tags", 2),
        ("sparsity_study", "2 jobs, 2 finished", 2),
        ("basis_analysis", "64 hidden units, input 32×64", 6),
    ],
)
def test_notebook_runs_headless(
    name: str,
    expected_text: str,
    min_images: int,
    tiny_multirun: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MFG_MULTIRUN_DIR", str(tiny_multirun))
    monkeypatch.setenv("MFG_RUN_DIR", str(tiny_multirun / "1"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = _execute(name, tiny_multirun.parent)
    text, images = _outputs(nb)
    assert expected_text in text
    assert images >= min_images
    if name == "sparsity_study":
        assert (tiny_multirun / "report" / "report.csv").is_file()
