"""The package layout holds: the import-linter contracts (pyproject.toml), the size of its units,
and no private name used outside its module.

The layers, top to bottom: the entry points, ``study``, ``analysis``, ``run``, ``models``,
``data``, ``pictures``, ``metrics``, ``motion``, ``flow | scene``, ``trajectory``, ``core``.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

PACKAGE = REPO / "src" / "mfg_lightning"
LINT = "import sys; from importlinter.cli import lint_imports_command; lint_imports_command()"
#: The modules allowed at the package's top level besides ``__init__``: its entry points.
ENTRY_POINTS = {
    "train", "train_flow", "evaluate", "evaluate_poses", "predict", "report", "analyze_basis",
    "reproduce", "measure",
}  # fmt: skip


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _name(path: Path) -> str:
    return ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(
        ".__init__"
    )


def _lint(root: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` with the project's contracts on the package under ``root/src``."""
    return subprocess.run(
        [sys.executable, "-c", LINT, "--no-cache", str(REPO / "pyproject.toml")],
        cwd=root, env={"PYTHONPATH": str(root / "src"), "PATH": "/usr/bin:/bin"},
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip


def test_contracts_hold() -> None:
    proc = _lint(REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


def test_a_wrong_way_import_and_a_cycle_break_the_contracts(tmp_path: Path) -> None:
    """core importing an entry point breaks the layers (named, both modules); two modules of a
    folder importing each other break the acyclic contract."""
    shutil.copytree(PACKAGE, tmp_path / "src" / "mfg_lightning",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    copy = tmp_path / "src" / "mfg_lightning"
    atomic = copy / "core" / "atomic.py"
    atomic.write_text(atomic.read_text() + "\n\ndef _up():\n    from mfg_lightning import train\n")
    tables = copy / "core" / "tables.py"
    tables.write_text(tables.read_text() + "\n\nfrom mfg_lightning.core import errors  # noqa\n")
    errors = copy / "core" / "errors.py"
    errors.write_text(errors.read_text() + "\n\nfrom mfg_lightning.core import tables  # noqa\n")
    proc = _lint(tmp_path)
    assert proc.returncode != 0
    out = proc.stdout
    assert "mfg_lightning.core is not allowed to import mfg_lightning.train" in out
    assert "- mfg_lightning.core.atomic -> mfg_lightning.train" in out
    assert "No cycles are allowed in mfg_lightning.core" in out
    assert "- .errors -> .tables" in out or "- .tables -> .errors" in out


def test_the_top_level_holds_only_entry_points() -> None:
    top = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__"}
    assert top == ENTRY_POINTS
    assert len(top) + 1 <= 12
    for name in top:
        text = (PACKAGE / f"{name}.py").read_text()
        assert "def main(" in text and 'if __name__ == "__main__":' in text, name
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == {"core", "scene", "flow", "data", "models", "motion", "trajectory",
                       "metrics", "pictures", "run", "analysis", "study"}  # fmt: skip
    for folder in folders:
        assert (PACKAGE / folder / "__init__.py").read_text().startswith('"""'), folder


@pytest.mark.parametrize("path", _modules(), ids=_name)
def test_units_a_reader_can_hold(path: Path) -> None:
    """No module over 800 lines, no function over 100."""
    text = path.read_text()
    assert len(text.splitlines()) <= 800
    long = [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.end_lineno - node.lineno + 1 > 100
    ]
    assert not long


def _private_uses(path: Path) -> list[str]:
    """Private names (one leading underscore) of other project modules this module uses: imported
    by name, or read as an attribute of an imported project module."""
    tree = ast.parse(path.read_text())
    found, modules = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mfg_lightning"):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.append(f"{node.module}.{alias.name}")
                elif alias.name[:1].islower():
                    modules.add(alias.asname or alias.name)  # perhaps a module
        elif isinstance(node, ast.Import):
            modules |= {a.asname or a.name for a in node.names if a.name.startswith("mfg_")}
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in modules
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
        ):
            found.append(f"{node.value.id}.{node.attr}")
    return found


@pytest.mark.parametrize("path", _modules(), ids=_name)
def test_no_private_name_crosses_modules(path: Path) -> None:
    assert not _private_uses(path)


def test_the_private_name_check_sees_both_forms(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from mfg_lightning.scene.seeding import _hidden\n"
        "from mfg_lightning.scene import camera\n"
        "camera._private(1)\n"
    )
    assert _private_uses(probe) == ["mfg_lightning.scene.seeding._hidden", "camera._private"]
