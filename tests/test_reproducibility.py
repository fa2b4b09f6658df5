"""A seed makes a run reproducible, and a run directory records what produced it.

The same seeded training, run twice in separate processes on the CPU, gives bit-identical
weights and metrics (data order across epochs, synthetic samples, initialisation); another
seed gives another run. The run directory holds the resolved config, the package version and
the git commit, and ``--cfg job`` prints the config that would run without running it.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch
import yaml

import mfg_lightning
from conftest import REPO, run_module
from mfg_lightning.core.config import compose
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.run.runs import build_model

pytestmark = pytest.mark.slow

# 12 optimiser steps over 5 batches per epoch: three epochs, each in its own shuffled order.
RUN = [
    "debug=tiny",
    "logger=none",
    "callbacks.rich_progress_bar=null",
    "+trainer.enable_progress_bar=false",
    "trainer.max_steps=12",
    "trainer.val_check_interval=6",
]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two runs with seed 7 and one with seed 8, each in its own process."""
    work = tmp_path_factory.mktemp("repro")
    out = {}
    for name, seed in (("a", 7), ("b", 7), ("other", 8)):
        out[name] = work / name
        run_module(
            "mfg_lightning.train", *RUN, f"seed={seed}", f"hydra.run.dir={out[name]}", cwd=work
        )
    return out


def _last(run: Path) -> dict:
    return torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)


def _metrics(run: Path) -> dict:
    return json.loads((run / "metrics.json").read_text())


def test_the_same_seed_gives_identical_weights_and_metrics(runs: dict[str, Path]) -> None:
    a, b = _last(runs["a"]), _last(runs["b"])
    assert a["global_step"] == b["global_step"] == 12
    for key, value in a["state_dict"].items():
        assert torch.equal(value, b["state_dict"][key]), key
    ma, mb = _metrics(runs["a"])["metrics"], _metrics(runs["b"])["metrics"]
    assert any(k.startswith("val/") for k in ma) and any(k.startswith("test/") for k in ma)
    assert ma == mb  # exactly, NaN-free: None stands for a non-finite value in metrics.json


def test_another_seed_gives_another_run(runs: dict[str, Path]) -> None:
    a, other = _last(runs["a"])["state_dict"], _last(runs["other"])["state_dict"]
    assert not all(torch.equal(v, other[k]) for k, v in a.items())
    assert _metrics(runs["a"])["metrics"] != _metrics(runs["other"])["metrics"]


def _git_head() -> str | None:
    proc = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=False
    )
    return proc.stdout.strip() if proc.returncode == 0 else None


def test_the_run_directory_records_config_version_and_commit(runs: dict[str, Path]) -> None:
    run = runs["a"]
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["seed"] == 7 and config["dataset"]["seed"] == 7  # resolved, not ${seed}
    assert config["trainer"]["max_steps"] == 12
    assert "${" not in (run / "config.yaml").read_text()
    head = _git_head()
    for info in (json.loads((run / "run_info.json").read_text()), _metrics(run)):
        assert info["mfg_lightning"] == mfg_lightning.__version__
        assert info["torch"] == torch.__version__
        assert info["git_commit"] == head
    run_info = json.loads((run / "run_info.json").read_text())
    assert run_info["seed"] == 7 and run_info["resumed_from"] is None


def test_cfg_job_prints_the_config_that_would_run_and_runs_nothing(tmp_path: Path) -> None:
    proc = run_module(
        "mfg_lightning.train", "seed=11", "resume=true", "trainer.max_steps=5", "--cfg", "job",
        cwd=tmp_path,
    )  # fmt: skip
    printed = yaml.safe_load(proc.stdout)
    assert printed["seed"] == 11 and printed["resume"] is True and printed["ckpt_path"] is None
    assert printed["trainer"]["max_steps"] == 5
    assert (
        printed["callbacks"]["last_checkpoint"]["_target_"]
        == "mfg_lightning.run.callbacks.LastCheckpoint"
    )
    assert not (tmp_path / "outputs").exists()  # nothing ran, no run directory


def test_samples_and_initialisation_depend_on_the_seed_only() -> None:
    def samples(seed: int, order: list[int]) -> dict[int, torch.Tensor]:
        dm = SyntheticDataModule(
            height=16, width=32, train_sequences=2, test_sequences=1, sequence_length=6, seed=seed
        )
        ds = dm.dataset("train")
        return {i: ds[i]["flow"] for i in order}

    forward, backward = samples(3, [0, 1, 2, 5]), samples(3, [5, 2, 1, 0])
    assert all(torch.equal(forward[i], backward[i]) for i in forward)
    assert not torch.equal(samples(4, [0])[0], forward[0])

    cfg = compose("train", ["debug=tiny", "seed=5", "paths.output_dir=unused"])

    def weights(seed: int) -> dict[str, torch.Tensor]:
        import lightning as L

        L.seed_everything(seed, verbose=False)
        return build_model(cfg).state_dict()

    w1, w2, w3 = weights(5), weights(5), weights(6)
    assert all(torch.equal(v, w2[k]) for k, v in w1.items())
    assert not all(torch.equal(v, w3[k]) for k, v in w1.items())
