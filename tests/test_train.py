"""Real, short trainings through the Hydra entry point."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import run_module
from mfg_lightning.core.config import compose

pytestmark = pytest.mark.slow


def _events(run_dir: Path) -> EventAccumulator:
    acc = EventAccumulator(str(run_dir / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    return acc


def test_short_training_writes_a_complete_run_directory(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run_module("mfg_lightning.train", "debug=tiny", f"hydra.run.dir={run}", cwd=tmp_path)
    # checkpoints (last and best), resolved config, metrics.json
    ckpts = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert "last.ckpt" in ckpts and any(c.startswith("best-") for c in ckpts)
    assert "dataset:" in (run / "config.yaml").read_text()
    assert "${" not in (run / "config.yaml").read_text()  # resolved
    payload = json.loads((run / "metrics.json").read_text())
    metrics = payload["metrics"]
    for key in (
        "test/trans_err",
        "test/rot_err",
        "test/baseline_trans_err",
        "test/active_fraction",
    ):
        assert metrics[key] is not None and metrics[key] >= 0, key
    assert payload["global_step"] == 4
    # TensorBoard event files, read back: every loss term, the active fraction and the pictures.
    acc = _events(run)
    scalars = set(acc.Tags()["scalars"])
    expected = {"train/loss", "train/l_t", "train/l_omega", "train/l_s", "train/w_t",
                "train/w_omega", "train/active_fraction", "val/trans_err", "val/rot_err",
                "train/lr"}  # fmt: skip
    assert expected <= scalars, expected - scalars
    # The default schedule: cosine from Adam's 1e-3 towards 0 over trainer.max_steps (4 here).
    lrs = [e.value for e in acc.Scalars("train/lr")]
    assert len(lrs) == 4 and lrs[0] == pytest.approx(1e-3)
    assert all(a > b for a, b in itertools.pairwise(lrs)) and lrs[-1] < 2e-4
    # The labelled figures of the default callbacks (tests/test_figures.py), not the earlier
    # strips (callbacks.figures.legacy_images=false).
    images = set(acc.Tags()["images"])
    expected = {"train/fields", "val/fields", "val/basis", "val/trajectory", "val/drift"}
    assert expected <= images, expected - images
    assert "train/flow" not in images
    # TensorBoard's HParams view: settings and final metrics of the run.
    hparams_runs = [
        EventAccumulator(str(f)) for f in sorted((run / "tensorboard").glob("events.out.*"))
    ]
    tags = set()
    for ea in hparams_runs:
        ea.Reload()
        try:
            tags |= set(ea.PluginTagToContent("hparams"))
        except KeyError:
            continue
    assert "_hparams_/session_start_info" in tags
    # The checkpoint carries the model config, so it can be rebuilt without the run directory.
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")
    assert ckpt["hyper_parameters"]["model_config"]["net"]["hidden_units"] == 64


def test_help_lists_the_config_groups(tmp_path: Path) -> None:
    out = run_module("mfg_lightning.train", "--help", cwd=tmp_path).stdout
    for group in ("dataset:", "model:", "trainer:", "logger:", "callbacks:", "debug:"):
        assert group in out


@pytest.mark.parametrize(
    "override,message",
    [
        ("dataset=nosuchdataset", "Could not find 'dataset/nosuchdataset'"),
        ("model.no_such_key=1", "no_such_key"),
        ("model.top_k=0", "model.top_k"),
        ("model.top_k=-0.1", "model.top_k"),
        ("model.loss.w_s=-1", "model.loss.w_s must be non-negative"),
        # The default cosine schedule follows max_steps; an epoch-counted run must say how long.
        ("trainer.max_steps=-1", "model.scheduler.T_max must be a positive number of steps"),
    ],
)
def test_bad_configuration_gives_a_clear_error(tmp_path: Path, override: str, message: str) -> None:
    proc = run_module(
        "mfg_lightning.train",
        "debug=tiny",
        override,
        f"hydra.run.dir={tmp_path / 'r'}",
        cwd=tmp_path,
        check=False,
    )
    assert proc.returncode != 0
    assert message in proc.stderr + proc.stdout
    assert not (tmp_path / "r" / "metrics.json").exists()


def test_config_composes_with_every_group_option() -> None:
    cfg = compose("train", ["trainer=gpu", "logger=none", "callbacks=none", "debug=fast_dev_run"])
    assert cfg.trainer.accelerator == "gpu"
    assert cfg.trainer.fast_dev_run is True
