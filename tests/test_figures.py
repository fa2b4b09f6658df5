"""The labelled TensorBoard figures: drawn by a callback from the steps' outputs, read
back from a real short training's event file at the validation steps."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from lightning.pytorch.loggers import TensorBoardLogger
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import quiet_trainer
from mfg_lightning.core.config import compose
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg import MFG
from mfg_lightning.models.mfg_module import MFGLitModule, StepFields
from mfg_lightning.pictures.colours import colour_wheel, flow_to_rgb
from mfg_lightning.pictures.fields import FIELD_COLUMNS, FieldRow, basis_figure, field_figure
from mfg_lightning.run.figures import TensorBoardFigures, sample_plan
from mfg_lightning.run.runs import build_model

FIGURES = ("val/fields", "val/basis", "val/trajectory", "val/drift")
LEGACY = ("flow", "v_t_gt", "v_t_pred", "v_omega_gt", "v_omega_pred", "hidden_activations")


def test_a_shared_maximum_gives_ground_truth_and_prediction_the_same_colours() -> None:
    field = np.zeros((2, 2, 2))
    field[0] = 1.0
    # saturated at its own maximum, pale at ten times it: flow_vis must not renormalise
    assert not np.array_equal(flow_to_rgb(field, 1.0), flow_to_rgb(field, 10.0))
    assert np.array_equal(flow_to_rgb(field), flow_to_rgb(field, 1.0))
    wheel = colour_wheel(33)
    assert wheel.shape == (33, 33, 4) and wheel[0, 0, 3] == 0 and wheel[16, 16, 3] == 255


def test_the_validation_samples_are_spread_and_the_same_every_time() -> None:
    # samples 0, 25, 50, 75 of 100 in batches of 32
    assert sample_plan(4, 100, 32) == {0: [0, 25], 1: [18], 2: [11]}
    assert sample_plan(4, 3, 8) == {0: [0, 1, 2]}  # fewer samples than rows: all of them
    assert sample_plan(0, 100, 8) == {} and sample_plan(4, 0, 8) == {}


def _row(i: int, h: int = 12, w: int = 24) -> FieldRow:
    f = np.random.default_rng(i).normal(size=(2, h, w))
    return FieldRow(f"seq\n{i}→{i + 1}", f, 2 * f, 2 * f, f / 10, f / 9, f / 5, np.abs(f[0]) > 1)


def test_the_field_figure_titles_its_columns_and_keys_every_row() -> None:
    fig = field_figure([_row(0), _row(1), _row(2)], "residual", "val fields")
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert titles == [*FIELD_COLUMNS, "residual", "colour key"]
    captions = [ax.get_xlabel() for ax in fig.axes if ax.get_xlabel()]
    assert len(captions) == 3 * 6 and all(
        c.startswith("max ") and c.endswith(" px") for c in captions
    )
    # ground truth and prediction of a field state one maximum
    assert captions[1] == captions[2] and captions[3] == captions[4]
    wheels = [t for ax in fig.axes for t in ax.texts if t.get_text() == "rim = max"]
    assert len(wheels) == 3  # one colour key per row


def test_the_basis_figure_draws_the_top_k_cut_and_the_units() -> None:
    acts = np.abs(np.random.default_rng(0).normal(size=50))
    units = list(np.argsort(-acts)[:5])
    fields = [np.ones((2, 8, 16)) * (i + 1) for i in range(5)]
    fig = basis_figure(acts, units, fields, fields, kept=10, title="basis")
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert any(label.startswith("top-k cut: 10 kept") for label in labels)
    assert any(label.startswith("active (> 0): 50 of 50") for label in labels)
    assert [ax.get_title() for ax in fig.axes[1:3]] == [
        f"unit {units[0]}: v_t",
        f"unit {units[0]}: v_ω",
    ]


def _module(image_every: int) -> MFGLitModule:
    torch.manual_seed(0)
    net = MFG(height=32, width=64, hidden_units=32, channels=(8, 8, 8, 16, 16))
    optimizer = functools.partial(torch.optim.Adam, lr=1e-3, fused=True)
    return MFGLitModule(net, MFGLoss(w_s=1.0), optimizer, image_log_every_n_steps=image_every)


def test_the_training_step_hands_its_fields_every_image_log_every_n_steps() -> None:
    model = _module(image_every=2)
    step, handed = model.training_step, []

    def training_step(batch, batch_idx):
        out = step(batch, batch_idx)
        handed.append(isinstance(out, dict) and isinstance(out["fields"], StepFields))
        return out

    model.training_step = training_step
    dm = SyntheticDataModule(height=32, width=64, batch_size=4, eval_batch_size=8,
                             train_sequences=1, test_sequences=1, sequence_length=12,
                             val_fraction=0.2)  # fmt: skip
    trainer = quiet_trainer(max_steps=4, log_every_n_steps=4, limit_val_batches=0)
    trainer.fit(model, datamodule=dm)
    assert handed == [True, False, True, False]  # every image_log_every_n_steps-th step


@pytest.mark.slow
def test_a_short_training_logs_the_figures_at_each_validation(tmp_path: Path) -> None:
    """The quick-start config at tiny sizes, its figure callback as configured (with the
    earlier strips on), a TensorBoard logger; the event file read back."""
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={tmp_path}"])
    model, dm = build_model(cfg), instantiate(cfg.dataset)
    figures = instantiate(cfg.callbacks.figures, legacy_images=True)
    assert isinstance(figures, TensorBoardFigures)
    logger = TensorBoardLogger(tmp_path, name="tb", version=0)
    trainer = quiet_trainer(logger=logger, callbacks=[figures], max_steps=4,
                            val_check_interval=2, log_every_n_steps=1)  # fmt: skip
    trainer.fit(model, datamodule=dm)
    acc = EventAccumulator(str(tmp_path / "tb" / "version_0"), size_guidance={"images": 0})
    acc.Reload()
    images = set(acc.Tags()["images"])
    legacy = {f"{stage}/{name}" for stage in ("train", "val") for name in LEGACY}
    assert {*FIGURES, "train/fields", *legacy} <= images, {*FIGURES, *legacy} - images
    # at every validation (not the sanity check), at the step of its numbers
    validations = [e.step for e in acc.Scalars("val/ate")]
    assert len(validations) == 2
    for tag in FIGURES:
        assert [e.step for e in acc.Images(tag)] == validations, tag
    assert [e.step for e in acc.Images("train/fields")] == [0, 2]  # image_log_every_n_steps
    field = acc.Images("val/fields")[-1]
    assert field.width >= 900 and field.height >= 400  # readable when TensorBoard halves it
