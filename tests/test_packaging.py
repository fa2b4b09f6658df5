"""A non-editable install (a wheel) carries the Hydra configs inside the package."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from conftest import REPO

pytestmark = pytest.mark.slow


def test_wheel_ships_the_configs(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation",
         "-w", str(tmp_path), "-q"],
        check=True, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    (wheel,) = tmp_path.glob("mfg_lightning-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for cfg in ("train.yaml", "evaluate.yaml", "model/mfg.yaml", "dataset/synthetic.yaml",
                "dataset/kitti.yaml", "experiment/paper_kitti.yaml"):  # fmt: skip
        assert f"mfg_lightning/conf/{cfg}" in names, cfg
    # Installed from the wheel, config_dir() finds the packaged copy, not a repository's.
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", str(wheel), "--no-deps", "-q", "--target",
         str(target)],
        check=True, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    out = subprocess.run(
        [sys.executable, "-c",
         "from mfg_lightning.core.config import config_dir; print(config_dir())"],
        cwd=tmp_path, env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"},
        capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    assert Path(out.stdout.strip()) == target / "mfg_lightning" / "conf"
