"""The LightningModule in-process: bad values never reach the weights."""

from __future__ import annotations

import lightning as L
import pytest
import torch

from conftest import quiet_trainer
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.run.agreed_steps import NonFiniteLossError
from mfg_lightning.run.runs import build_model
from module_helpers import corrupt_datamodule, small_datamodule, small_module

#: 15 NaN pixels and 1 infinite pixel per sample
CorruptDataModule = corrupt_datamodule(slice(0, 3), slice(0, 5), inf=((0, 5, 5),))


def _module(loss: MFGLoss | None = None, **kw) -> MFGLitModule:
    return small_module(loss, fused=False, **kw)


def _dm(cls=SyntheticDataModule) -> SyntheticDataModule:
    return small_datamodule(cls)


def _trainer(tmp_path, steps: int = 3) -> L.Trainer:
    return quiet_trainer(
        max_steps=steps,
        # the module logs its step diagnostics on the steps the loggers write
        log_every_n_steps=1,
        limit_val_batches=1,
        default_root_dir=tmp_path,
    )


def test_non_finite_flow_is_masked_counted_and_never_reaches_the_weights(tmp_path) -> None:
    torch.manual_seed(0)
    model = _module()
    trainer = _trainer(tmp_path)
    trainer.fit(model, datamodule=_dm(CorruptDataModule))
    assert trainer.global_step == 3
    assert all(torch.isfinite(p).all() for p in model.parameters())
    # 15 NaN pixels and 1 infinite pixel per sample; 3 steps over 9 training samples.
    assert float(trainer.callback_metrics["train/nonfinite_flow_pixels"]) == 16 * 9
    assert float(trainer.callback_metrics["val/nonfinite_flow_pixels"]) == 16 * 2


class NaNLoss(MFGLoss):
    """Fault injection: the loss of the first ``bad_steps`` calls is NaN."""

    def __init__(self, bad_steps: int) -> None:
        super().__init__(w_s=1.0)
        self.calls, self.bad_steps = 0, bad_steps

    def forward(self, *args):
        terms = super().forward(*args)
        self.calls += 1
        if self.calls <= self.bad_steps:
            return terms._replace(total=terms.total * float("nan"))
        return terms


def test_a_non_finite_loss_skips_the_optimiser_step(tmp_path) -> None:
    torch.manual_seed(0)
    model = _module(NaNLoss(bad_steps=2))
    before = [p.detach().clone() for p in model.parameters()]
    trainer = quiet_trainer(
        max_steps=2, limit_train_batches=2, limit_val_batches=0, default_root_dir=tmp_path
    )
    trainer.fit(model, datamodule=_dm())
    for p, q in zip(model.parameters(), before, strict=True):
        assert torch.equal(p, q)


def test_persistent_non_finite_losses_stop_the_run_naming_the_samples(tmp_path) -> None:
    model = _module(NaNLoss(bad_steps=100), max_consecutive_nonfinite=3)
    with pytest.raises(
        NonFiniteLossError, match=r"3 consecutive non-finite losses.*synthetic/train"
    ):
        _trainer(tmp_path, steps=10).fit(model, datamodule=_dm())


def test_predict_motion_matches_closed_form_recovery() -> None:
    model = _module().eval()
    batch = _dm().dataset("test")[0]
    with torch.no_grad():
        t, w, out = model.predict_motion(batch["flow"][None], batch["intrinsics"][None])
    assert t.shape == w.shape == (1, 3)
    assert out.v_t.shape == (1, 2, 32, 64)


def test_batch_transfer_is_skipped_on_a_cpu_only() -> None:
    """On a CPU the batch is handed through untouched (the transfer would be a no-op costing a
    recursive walk per step); any other device still gets Lightning's transfer."""
    module = _module()
    batch = {"flow": torch.zeros(1, 2, 4, 4), "sequence": ["00"], "frame": torch.tensor([3])}
    assert module.transfer_batch_to_device(batch, torch.device("cpu"), 0) is batch
    moved = module.transfer_batch_to_device(batch, torch.device("meta"), 0)
    assert moved["flow"].device.type == "meta" and moved["frame"].device.type == "meta"
    assert moved["sequence"] == ["00"]


def test_top_k_has_one_knob() -> None:
    """model.top_k is the setting; a top_k given to the network as well is refused, not
    silently overwritten."""
    from mfg_lightning.core.config import compose

    cfg = compose("train", ["debug=tiny", "paths.output_dir=/tmp/unused", "+model.net.top_k=0.1"])
    with pytest.raises(Exception, match="model.net.top_k=0.1 .* set model.top_k instead"):
        build_model(cfg)
