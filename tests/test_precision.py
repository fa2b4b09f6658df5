"""Precision as a setting: float32 geometry, losses, object motion and metrics under any
autocast; a true low precision refused at setup; ``16-mixed`` from its first step; no host
synchronisation in a training step outside the logging steps. The accepted values and the GPU
configs: tests/test_trainer_settings.py."""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from hydra.utils import instantiate
from lightning.pytorch.plugins.precision import MixedPrecision
from torchmetrics import MeanMetric

from conftest import quiet_trainer
from mfg_lightning.core import geometry as G
from mfg_lightning.core.config import compose
from mfg_lightning.data.sample import INTRINSICS_HOST as HOST_INTRINSICS
from mfg_lightning.data.sample import SampleError, sanitize_flow
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.metrics.frame_errors import FiniteMean
from mfg_lightning.models.losses import MFGLoss, sparsity_count
from mfg_lightning.models.mfg import MFG, bilinear_matrix, upsample_bilinear
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.motion.object_motion import extract_object_motion
from mfg_lightning.run.agreed_steps import AgreedSteps, NonFiniteLossError
from mfg_lightning.run.checkpoints import module_from_checkpoint
from mfg_lightning.run.precision import (
    FP16_INIT_SCALE,
    PrecisionSetup,
    fit_grad_scaler,
)
from mfg_lightning.run.runs import build_model
from module_helpers import corrupt_datamodule, small_datamodule, small_module

#: torch.autocast dtypes on the CPU: what bf16-mixed and 16-mixed run the encoder in.
LOW = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}
H, W = 48, 128


def _motions(n: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random driving-like motions (m, rad per frame) and KITTI-like intrinsics at 48 × 128."""
    g = torch.Generator().manual_seed(seed)
    t = torch.randn(n, 3, generator=g) * torch.tensor([0.05, 0.02, 0.5])
    w = torch.randn(n, 3, generator=g) * torch.tensor([0.005, 0.02, 0.005])
    K = torch.tensor([74.145, 74.145, 62.179, 22.867]).expand(n, 4)
    return t, w, K


@pytest.mark.parametrize("precision", sorted(LOW))
def test_recovering_exact_fields_under_autocast_gives_float32_answer(precision: str) -> None:
    """Measured before the geometry widened its arguments: in bf16 the recovery erred by up to
    2.2e-3 m / 8.5e-5 rad (fx 74.145 cast to 74.0); under autocast it now gives float32's
    answer."""
    t, w, K = _motions()
    v_t = G.translational_field(t, K, H, W)
    v_w = G.rotational_field(w, K, H, W)
    t32, w32 = G.recover_motion(v_t, v_w, K)
    with torch.autocast("cpu", dtype=LOW[precision]):
        fields = G.translational_field(t, K, H, W), G.rotational_field(w, K, H, W)
        t_mix, w_mix = G.recover_motion(*fields, K)
    assert fields[0].dtype == fields[1].dtype == t_mix.dtype == w_mix.dtype == torch.float32
    assert (t_mix - t32).abs().max() <= 1e-5
    assert (w_mix - w32).abs().max() <= 1e-7
    # and float32's answer is the truth to float32 rounding
    assert (t32 - t).abs().max() < 1e-5 and (w32 - w).abs().max() < 1e-6


def test_low_precision_arguments_are_widened_to_float32() -> None:
    t, w, K = _motions(8)
    field = G.translational_field(t.bfloat16(), K.bfloat16(), H, W)
    assert field.dtype == torch.float32
    # float64 stays float64, and the float32 path is the undecorated function's
    assert G.so3_exp(w.double()).dtype == torch.float64
    assert torch.equal(G.so3_exp(w), G.so3_exp.__wrapped__(w))


@pytest.mark.parametrize("precision", sorted(LOW))
def test_decoders_losses_and_object_motion_run_in_float32(precision: str) -> None:
    torch.manual_seed(0)
    net = MFG(height=32, width=64, hidden_units=32, channels=(8, 8, 8, 16, 16)).eval()
    flow = torch.randn(2, 2, 32, 64) * 3
    with torch.autocast("cpu", dtype=LOW[precision]):
        out = net(flow)
        decoded = net.decode(out.hidden)
    # The encoder ran in the low precision; the fields come out in float32, as the float32
    # decoders give them from those hidden units.
    assert out.hidden.dtype == LOW[precision]
    assert out.v_t.dtype == out.v_omega.dtype == torch.float32
    reference = net.decode(out.hidden.float())
    assert torch.equal(decoded[0], reference[0]) and torch.equal(decoded[1], reference[1])

    loss = MFGLoss(w_s=100.0)
    gt = (torch.randn_like(out.v_t), torch.randn_like(out.v_omega) * 0.1)
    with torch.autocast("cpu", dtype=LOW[precision]):
        terms = loss(out.v_t, out.v_omega, *gt, out.hidden)
        count = sparsity_count(out.hidden)
    plain = loss(out.v_t, out.v_omega, *gt, out.hidden.float())
    for mixed, full in zip(terms, plain, strict=True):
        assert mixed.dtype == torch.float32 and torch.equal(mixed, full)
    assert torch.equal(count, sparsity_count(out.hidden.float()))

    depth = torch.rand(2, 32, 64) * 30 + 2
    with torch.autocast("cpu", dtype=LOW[precision]):
        res = extract_object_motion(flow, out.v_t, out.v_omega, depth)
    ref = extract_object_motion(flow, out.v_t, out.v_omega, depth)
    assert res.residual.dtype == torch.float32 and torch.equal(res.residual, ref.residual)
    assert torch.equal(res.mask, ref.mask)


def test_finite_mean_is_mean_metric_without_its_host_check() -> None:
    values = [torch.rand(5, dtype=torch.float64), torch.rand(3, dtype=torch.float64)]
    ours, theirs = FiniteMean(), MeanMetric()
    for v in values:
        ours.update(v, weight=4)
        theirs.update(v, weight=4)
    assert torch.equal(ours.compute(), theirs.compute())
    # NaN values are left out, as MeanMetric's default does, and counted
    ours.update(torch.tensor([float("nan"), 1.0]))
    theirs = MeanMetric(nan_strategy="ignore")
    for v in [*values, torch.tensor([float("nan"), 1.0])]:
        theirs.update(v, weight=4 if v.dtype == torch.float64 else 1)
    assert ours.compute().item() == pytest.approx(theirs.compute().item(), rel=1e-6)
    assert int(ours.nan_count) == 1


def test_a_trainer_with_a_true_low_precision_is_refused_at_setup() -> None:
    model = _module()
    trainer = quiet_trainer(max_steps=1, precision="bf16-true", callbacks=[PrecisionSetup()])
    with pytest.raises(ValueError, match="trainer.precision=bf16-true"):
        trainer.fit(model, datamodule=_dm())


# --------------------------------------------------------------------------------------------
# Training and evaluation under each precision
# --------------------------------------------------------------------------------------------


def _module(loss: MFGLoss | None = None, **kw) -> MFGLitModule:
    torch.manual_seed(0)
    return small_module(loss, **kw)


def _dm(cls: type = SyntheticDataModule) -> SyntheticDataModule:
    return small_datamodule(cls)


def _precision_options(precision: str) -> dict:
    """Trainer options for ``precision`` on a CPU: Lightning turns ``precision="16-mixed"`` on a
    CPU into bf16-mixed, so fp16 autocast is asked for with its plugin."""
    if precision == "16-mixed":
        return {"plugins": [MixedPrecision("16-mixed", "cpu")], "callbacks": [PrecisionSetup()]}
    return {"precision": precision, "callbacks": [PrecisionSetup()]}


@pytest.mark.parametrize("precision", ["32-true", "bf16-mixed", "16-mixed"])
def test_tiny_training_under_each_precision_steps_from_the_first_step(precision: str) -> None:
    model = _module()
    before = [p.detach().clone() for p in model.parameters()]
    trainer = quiet_trainer(
        max_steps=3, limit_val_batches=1, log_every_n_steps=1, **_precision_options(precision)
    )
    trainer.fit(model, datamodule=_dm())
    assert trainer.precision == precision
    assert math.isfinite(float(trainer.callback_metrics["train/loss"]))
    assert math.isfinite(float(trainer.callback_metrics["val/trans_err"]))
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert not any(torch.equal(p, q) for p, q in zip(model.parameters(), before, strict=True))
    # Every one of the 3 steps updated the weights (fused Adam counts only the steps it took).
    state = trainer.optimizers[0].state[next(model.parameters())]
    assert float(state["step"]) == 3
    assert float(trainer.callback_metrics["train/skipped_steps"]) == 0
    if precision == "16-mixed":
        scaler = trainer.precision_plugin.scaler
        # started at the fitted scale, not torch's 65536, and never had to back off
        assert scaler.get_scale() == FP16_INIT_SCALE


def test_only_lightnings_default_grad_scaler_is_refitted() -> None:
    default = MixedPrecision("16-mixed", "cpu")
    assert default.scaler.get_scale() == 2.0**16  # torch's, which overflows fp16 at first
    assert fit_grad_scaler(default) and default.scaler.get_scale() == FP16_INIT_SCALE
    given = MixedPrecision("16-mixed", "cpu", scaler=torch.amp.GradScaler("cpu", init_scale=8.0))
    assert not fit_grad_scaler(given) and given.scaler.get_scale() == 8.0
    assert not fit_grad_scaler(MixedPrecision("bf16-mixed", "cpu"))


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A float32-trained tiny model (the debug=tiny config, 40 steps) as a checkpoint."""
    out = tmp_path_factory.mktemp("ckpt")
    cfg = compose("train", ["debug=tiny", f"paths.output_dir={out}"])
    torch.manual_seed(0)
    model = build_model(cfg)
    dm = instantiate(cfg.dataset)
    trainer = quiet_trainer(max_steps=40, limit_val_batches=0)
    trainer.fit(model, datamodule=dm)
    path = out / "tiny.ckpt"
    trainer.save_checkpoint(path)
    return path


@pytest.mark.parametrize("precision", sorted(LOW))
def test_a_float32_checkpoint_evaluates_the_same_under_mixed_precision(
    tiny_checkpoint: Path, precision: str
) -> None:
    """Test ATE and RPE within 1 % of the float32 evaluation (the encoder alone runs in the low
    precision; measured: well under 0.1 %)."""
    results = {}
    for p in ("32-true", precision):
        model = module_from_checkpoint(tiny_checkpoint)
        dm = instantiate(model.dataset_config)
        trainer = quiet_trainer(**_precision_options(p))
        trainer.test(model, datamodule=dm)
        results[p] = {k: float(v) for k, v in trainer.callback_metrics.items()}
    ref, mixed = results["32-true"], results[precision]
    for name in ("test/ate", "test/rpe_trans", "test/rpe_rot", "test/trans_err"):
        assert math.isfinite(ref[name]) and ref[name] > 0, name
        assert mixed[name] == pytest.approx(ref[name], rel=0.01), name


# --------------------------------------------------------------------------------------------
# Non-finite values in training
# --------------------------------------------------------------------------------------------

#: 6 NaN pixels per sample, masked and counted by the module
CorruptDataModule = corrupt_datamodule(slice(0, 2), slice(0, 3))


class NaNLoss(MFGLoss):
    """Fault injection: the loss of the calls numbered in ``bad`` (from 1) is NaN."""

    def __init__(self, bad: set[int]) -> None:
        super().__init__(w_s=1.0)
        self.calls, self.bad = 0, bad

    def forward(self, *args):
        terms = super().forward(*args)
        self.calls += 1
        return terms._replace(total=terms.total * float("nan")) if self.calls in self.bad else terms


@pytest.mark.parametrize("precision", ["32-true", "bf16-mixed"])
def test_masked_flow_and_a_non_finite_loss_are_counted(precision: str) -> None:
    """Masked NaN flow in every step and a non-finite loss among them: the flow's pixels are
    counted, the step with the non-finite loss is skipped, and no NaN reaches the weights."""
    model = _module(NaNLoss(bad={2}))
    trainer = quiet_trainer(
        max_steps=5, log_every_n_steps=5, limit_val_batches=0, precision=precision
    )
    trainer.fit(model, datamodule=_dm(CorruptDataModule))
    # 6 NaN pixels in each of 4 + 4 + 1 + 4 + 4 samples, 1 skipped step.
    assert float(trainer.callback_metrics["train/nonfinite_flow_pixels"]) == 6 * 17
    assert float(trainer.callback_metrics["train/skipped_steps"]) == 1
    assert all(torch.isfinite(p).all() for p in model.parameters())


class Snapshots(L.Callback):
    """The weights and Adam's step count after every training step."""

    def __init__(self) -> None:
        self.weights: list[list[torch.Tensor]] = []
        self.steps: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, *args) -> None:
        self.weights.append([p.detach().clone() for p in pl_module.parameters()])
        state = trainer.optimizers[0].state[next(pl_module.parameters())]
        # no state before the first optimiser step (a first micro-batch)
        self.steps.append(float(state["step"]) if "step" in state else 0.0)


def test_a_non_finite_loss_is_skipped_inside_the_fused_optimiser() -> None:
    """The replacement of the host-side skip: the step whose loss is NaN leaves weights and Adam's
    state as the step before left them (after a real step, so Adam's momentum is non-zero),
    and training goes on."""
    model = _module(NaNLoss(bad={2}))
    snaps = Snapshots()
    trainer = quiet_trainer(max_steps=3, limit_val_batches=0, callbacks=[snaps])
    trainer.fit(model, datamodule=_dm())
    assert snaps.steps == [1.0, 1.0, 2.0]
    for p, q in zip(snaps.weights[0], snaps.weights[1], strict=True):
        assert torch.equal(p, q)
    assert not any(
        torch.equal(p, q) for p, q in zip(snaps.weights[1], snaps.weights[2], strict=True)
    )
    assert not hasattr(trainer.optimizers[0], "found_inf")  # nothing left for a later step


def test_an_accumulated_step_with_a_non_finite_micro_batch_is_skipped() -> None:
    """Two micro-batches per optimiser step, the first one's loss NaN, the second finite: the
    optimiser step is skipped (weights and Adam's step count untouched), the next one taken."""
    model, snaps = _module(NaNLoss(bad={1})), Snapshots()
    steps = AgreedSteps()
    trainer = quiet_trainer(
        max_steps=2, limit_val_batches=0, callbacks=[snaps, steps], accumulate_grad_batches=2
    )
    trainer.fit(model, datamodule=_dm())
    assert (steps.skipped, steps.consecutive) == (1, 0)
    # Snapshots sees every micro-batch (an epoch of 3: the last one steps alone): the first
    # optimiser step (batches 1-2) was skipped, the second taken
    assert snaps.steps == [0.0, 0.0, 1.0]
    assert all(torch.equal(p, q) for p, q in zip(snaps.weights[0], snaps.weights[1], strict=True))
    assert not any(
        torch.equal(p, q) for p, q in zip(snaps.weights[1], snaps.weights[2], strict=True)
    )


def test_persistent_non_finite_losses_stop_the_run_at_a_logging_step() -> None:
    model = _module(NaNLoss(bad=set(range(1, 100))), max_consecutive_nonfinite=3)
    trainer = quiet_trainer(max_steps=10, log_every_n_steps=1, limit_val_batches=0)
    with pytest.raises(NonFiniteLossError, match=r"3 consecutive non-finite losses.*synthetic/"):
        trainer.fit(model, datamodule=_dm())
    assert all(torch.isfinite(p).all() for p in model.parameters())


def test_sanitize_flow_counts_in_a_tensor() -> None:
    flow = torch.zeros(2, 2, 4, 4)
    flow[0, 1, 2, 3] = float("inf")
    clean, valid, n_bad = sanitize_flow(flow, torch.ones(2, 4, 4, dtype=torch.bool))
    assert isinstance(n_bad, torch.Tensor) and int(n_bad) == 1
    assert torch.isfinite(clean).all() and not valid[0, 2, 3] and valid.sum() == 31


def _batch(bad_pose: bool = False) -> dict:
    ds = _dm().dataset("train")
    batch = torch.utils.data.default_collate([ds[0], ds[1]])
    if bad_pose:
        batch["pose"][1, 0, 3] = float("nan")
    return batch


def test_batch_checks_refuse_a_bad_batch_naming_it() -> None:
    """A training batch with a non-finite pose is refused at the start of its step, by its own
    sample ids; a good one passes."""
    model, steps = _module(), AgreedSteps()
    one_process = quiet_trainer()
    bad = _batch(bad_pose=True)
    with pytest.raises(SampleError, match=rf"{bad['sample_id'][1]}: 'pose' has non-finite"):
        steps.on_train_batch_start(one_process, model, bad, 0)
    steps.on_train_batch_start(one_process, model, _batch(), 1)


def test_the_batch_keeps_its_host_intrinsics_on_another_device() -> None:
    batch = _batch()
    moved = _module().transfer_batch_to_device(batch, torch.device("meta"), 0)
    assert moved["intrinsics"].device.type == "meta"
    assert moved[HOST_INTRINSICS] is batch["intrinsics"]


# --------------------------------------------------------------------------------------------
# Deterministic CUDA, the GPU configs
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("align_corners", [True, False])
def test_the_deterministic_upsampling_is_bilinear_interpolation(align_corners: bool) -> None:
    """On CUDA with deterministic algorithms on, the fields are upsampled by two matrix products
    (F.interpolate's CUDA backward has no deterministic kernel): the same values and gradients."""
    f = torch.randn(3, 2, 24, 64, requires_grad=True)
    ref = F.interpolate(f, size=(48, 128), mode="bilinear", align_corners=align_corners)
    M_h, M_w = bilinear_matrix(24, 48, align_corners), bilinear_matrix(64, 128, align_corners)
    ours = M_h @ f @ M_w.T
    assert (ours - ref).abs().max() < 1e-6
    g = torch.randn_like(ref)
    (grad_ref,) = torch.autograd.grad(ref, f, g)
    (grad_ours,) = torch.autograd.grad(ours, f, g)
    assert (grad_ours - grad_ref).abs().max() < 1e-4
    # the CPU keeps F.interpolate
    assert torch.equal(upsample_bilinear(f, (48, 128), align_corners), ref)
