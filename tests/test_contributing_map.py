"""CONTRIBUTING's map (the block under "Layout") names the home of every module of the package:
a module added without a word there fails here, by name, so the map a newcomer reads is the
package as it is."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from conftest import REPO

PACKAGE = REPO / "src" / "mfg_lightning"
TOP = "<top level>"


def map_entries(contributing: str) -> dict[str, str]:
    """The map's entries under ``src/mfg_lightning/``: each folder's text (its line and the
    indented lines that continue it) by folder name, the entry points' by :data:`TOP`."""
    block = contributing.split("## Layout", 1)[1].split("```", 2)[1]
    entries: dict[str, str] = {}
    current = None
    for line in block.splitlines():
        if not line.startswith(" "):  # a top-level path of the repository
            current = TOP if line.startswith("src/mfg_lightning/") else None
            continue
        if current is None:
            continue
        if (m := re.match(r"^  (\w+)/\s", line)) is not None:
            current = m.group(1)
        entries[current] = f"{entries.get(current, '')}\n{line}"
    return entries


def unmapped(entries: dict[str, str], package: Path = PACKAGE) -> list[str]:
    """The package's modules (``folder/module.py``) that their folder's entry does not name."""
    missing = []
    for path in sorted(package.rglob("*.py")):
        if path.name == "__init__.py" or "__pycache__" in path.parts:
            continue
        rel = path.relative_to(package)
        home = TOP if len(rel.parts) == 1 else rel.parts[0]
        if not re.search(rf"(?<![\w.]){re.escape(path.name)}\b", entries.get(home, "")):
            missing.append(str(rel))
    return missing


def _contributing() -> str:
    return (REPO / "CONTRIBUTING.md").read_text()


def test_every_folder_has_an_entry() -> None:
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders <= set(map_entries(_contributing())) - {TOP}


def test_every_module_is_named_in_its_folders_entry() -> None:
    missing = unmapped(map_entries(_contributing()))
    assert not missing, f"add them to CONTRIBUTING.md's map: {', '.join(missing)}"


def test_a_module_missing_from_the_map_is_found(tmp_path: Path) -> None:
    """The check itself: a module added to a copy of a folder, and a name taken out of the map,
    are each reported; a name that only ends like another (``optical_flow.py`` for ``flow.py``)
    does not count as it."""
    entries = map_entries(_contributing())
    package = tmp_path / "mfg_lightning"
    (package / "motion").mkdir(parents=True)
    for name in ("baselines.py", "object_motion.py", "flow.py"):
        (package / "motion" / name).write_text('"""x"""\n')
    (package / "train.py").write_text('"""x"""\n')
    assert unmapped(entries, package) == ["motion/flow.py"]
    entries["motion"] = entries["motion"].replace("baselines.py", "baselines")
    assert unmapped(entries, package) == ["motion/baselines.py", "motion/flow.py"]


@pytest.mark.parametrize("folder", ["study", "run", "metrics"])
def test_an_entry_ends_at_the_next_folder(folder: str) -> None:
    entries = map_entries(_contributing())
    assert entries[folder].lstrip("\n").startswith(f"  {folder}/")
    assert not re.search(r"^  \w+/", entries[folder].lstrip("\n")[3:], re.MULTILINE)
