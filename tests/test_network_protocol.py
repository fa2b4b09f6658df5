"""A second encoder is one class: anything with the MotionFieldNetwork members trains, evaluates
and is checked through the training module, unchanged."""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor, nn

from conftest import quiet_trainer
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg import ALL_UNITS, MFG, MFGOutput, MotionFieldNetwork, fields_at_each_k
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.run.agreed_steps import AgreedSteps
from module_helpers import small_datamodule


class PooledEncoder(nn.Module):
    """A toy network: one strided convolution, a max-pool to ``hidden_units`` units, and one
    bias-free linear decoder per field at the full input resolution."""

    def __init__(self, height: int = 32, width: int = 64, hidden_units: int = 8) -> None:
        super().__init__()
        self.height, self.width, self.hidden_units = height, width, hidden_units
        self.conv = nn.Conv2d(2, hidden_units, 5, stride=4, padding=2)
        self.fields = nn.Linear(hidden_units, 2 * 2 * height * width, bias=False)

    def encode(self, flow: Tensor) -> tuple[Tensor, Tensor]:
        hidden_map = torch.relu(self.conv(flow))
        return hidden_map.amax(dim=(2, 3)), hidden_map

    def decode(self, hidden: Tensor) -> tuple[Tensor, Tensor]:
        v = self.fields(hidden.float()).view(-1, 2, 2, self.height, self.width)
        return v[:, 0], v[:, 1]

    def forward(self, flow: Tensor) -> MFGOutput:
        return fields_at_each_k(self, flow, [ALL_UNITS])[0]


def test_the_paper_network_has_the_named_interface() -> None:
    assert isinstance(MFG(height=32, width=64, hidden_units=8), MotionFieldNetwork)
    assert not isinstance(nn.Linear(2, 2), MotionFieldNetwork)


def test_a_toy_encoder_trains_and_evaluates_through_the_interface(tmp_path) -> None:
    torch.manual_seed(0)
    net = PooledEncoder()
    assert isinstance(net, MotionFieldNetwork)
    module = MFGLitModule(
        net, MFGLoss(w_s=1.0), functools.partial(torch.optim.Adam, lr=1e-2, fused=True),
        top_k=0.5, image_log_every_n_steps=0,
    )  # fmt: skip
    before = [p.detach().clone() for p in module.parameters()]
    trainer = quiet_trainer(
        max_steps=3, log_every_n_steps=1, limit_val_batches=1, callbacks=[AgreedSteps()],
        default_root_dir=tmp_path,
    )  # fmt: skip
    trainer.fit(module, datamodule=small_datamodule())
    assert trainer.global_step == 3
    assert not any(torch.equal(p, q) for p, q in zip(module.parameters(), before, strict=True))
    for name in ("train/loss", "val/loss", "val/trans_err", "val/rot_err"):
        assert math.isfinite(float(trainer.callback_metrics[name])), name
    # top-k applies at evaluation: half of the 8 units at most stay active
    module.eval()
    with torch.no_grad():
        out = module(torch.randn(2, 2, 32, 64))
    assert int((out.hidden > 0).sum(1).max()) <= 4
    assert out.v_t.shape == out.v_omega.shape == (2, 2, 32, 64)
