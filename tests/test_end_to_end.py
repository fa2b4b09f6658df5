"""experiment=end_to_end: the learned flow network and MFG trained together on MFG's loss
(mfg_lightning.models.end_to_end, on mfg_lightning.data.image_pairs)."""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import quiet_trainer, run_module
from mfg_lightning.data import transforms
from mfg_lightning.data.image_pairs import ImagePairsDataModule
from mfg_lightning.flow.learned import LearnedFlowEstimator, model_input_flow, save_weights
from mfg_lightning.flow.pwc import PWCConfig, PWCFlowNet
from mfg_lightning.models.end_to_end import EndToEndLitModule
from mfg_lightning.models.losses import MFGLoss
from mfg_lightning.models.mfg import MFG

#: MFG's input in these tests (debug=tiny's) and the render size, four times it
MODEL_HW, IMAGE_HW = (32, 64), (128, 256)


def test_mfg_reads_the_flow_that_flow_learned_gives_a_two_stage_mfg(tmp_path: Path) -> None:
    """The end-to-end step's flow (with gradients) is the two-stage pipeline's: the estimator's
    flow at the image size, resized to the model input by the dataset's own resize_flow."""
    small = PWCConfig(pyramid=(8, 8, 12, 16), decoder=(16, 16), context=(8, 8), dilations=(1, 2))
    torch.manual_seed(0)
    weights = save_weights(tmp_path / "net.pt", PWCFlowNet(small))
    estimator = LearnedFlowEstimator(str(weights), device="cpu")
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 256, (2, *IMAGE_HW, 3), dtype=np.uint8)
    full = estimator(a, b)
    expected, valid = transforms.resize_flow(full, np.ones(IMAGE_HW, bool), *MODEL_HW)
    assert valid.all()

    net = estimator.net()
    image0, image1 = (torch.from_numpy(x).permute(2, 0, 1)[None].float() / 255 for x in (a, b))
    levels, image_flow = net.levels_and_estimate(image0, image1)
    flow = model_input_flow(image_flow, *MODEL_HW)
    assert flow.requires_grad and levels[-1].shape[-2:] == MODEL_HW
    torch.testing.assert_close(flow[0].permute(1, 2, 0).detach().numpy(), expected,
                               atol=1e-4, rtol=1e-4)  # fmt: skip


@pytest.fixture(scope="module")
def pairs(tmp_path_factory: pytest.TempPathFactory) -> ImagePairsDataModule:
    """A tiny rendered split (one 10-frame training world, its 4-pair validation tail), cached."""
    cache = tmp_path_factory.mktemp("cache")
    data = ImagePairsDataModule(
        *MODEL_HW, train_sequences=1, test_sequences=1, sequence_length=10, val_fraction=0.4,
        batch_size=4, eval_batch_size=8, prepare_workers=0, cache_dir=str(cache),
    )  # fmt: skip
    for split in ("train", "val"):  # (the test split is not needed here)
        data.dataset(split).precompute_flow(progress=False)
    return data


def _module(**settings: object) -> EndToEndLitModule:
    torch.manual_seed(0)
    net = MFG(*MODEL_HW, hidden_units=64, channels=(8, 8, 16, 16, 32))
    return EndToEndLitModule(
        net=net, loss=MFGLoss(), optimizer=partial(torch.optim.Adam, lr=1e-3), flow_lr=5e-5,
        image_log_every_n_steps=0, **settings,
    )  # fmt: skip


def _flow_state(module: EndToEndLitModule) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in module.flow_net.state_dict().items()}


def _val_flow_epe(module: EndToEndLitModule, data: ImagePairsDataModule) -> float:
    metrics = quiet_trainer().validate(module, datamodule=data, verbose=False)[0]
    assert np.isfinite(metrics["val/ate"])  # MFG's pose metrics beside the flow's
    assert metrics["val/flow_epe_noc"] <= metrics["val/flow_epe"]  # KITTI's noc and all
    return float(metrics["val/flow_epe"])


def test_the_flow_network_learns_from_mfgs_loss_and_its_error_stays_bounded(
    pairs: ImagePairsDataModule,
) -> None:
    """Four steps on MFG's loss alone (no flow term) change every tensor of the flow network
    (its only teacher is the pose loss, through the flow MFG reads), and its end-point error
    against the exact flow after them is finite and within 1.5× of the shipped network's."""
    module = _module(flow_loss_weight=0.0)
    before_epe = _val_flow_epe(module, pairs)
    before = _flow_state(module)
    quiet_trainer(max_steps=4, limit_val_batches=0).fit(module, datamodule=pairs)
    after = module.flow_net.state_dict()
    unchanged = [k for k, v in before.items() if torch.equal(v, after[k])]
    assert not unchanged, unchanged
    after_epe = _val_flow_epe(module, pairs)
    print(f"flow EPE before {before_epe:.4f} px, after {after_epe:.4f} px")
    assert np.isfinite(after_epe) and after_epe <= 1.5 * before_epe, (before_epe, after_epe)


def test_the_frozen_warm_up_trains_mfg_and_leaves_the_flow_network_as_it_was(
    pairs: ImagePairsDataModule,
) -> None:
    module = _module(freeze_flow_steps=2, flow_loss_weight=1.0)
    flow_before = _flow_state(module)
    mfg_before = {k: v.clone() for k, v in module.net.state_dict().items()}
    quiet_trainer(max_steps=2, limit_val_batches=0).fit(module, datamodule=pairs)
    for k, v in module.flow_net.state_dict().items():
        assert torch.equal(v, flow_before[k]), k
    assert any(not torch.equal(v, mfg_before[k]) for k, v in module.net.state_dict().items())


def test_the_flow_term_joins_the_loss_once_the_network_trains(
    pairs: ImagePairsDataModule,
) -> None:
    module = _module(freeze_flow_steps=1, flow_loss_weight=0.5)
    trainer = quiet_trainer(max_steps=2, limit_val_batches=0, log_every_n_steps=1)
    trainer.fit(module, datamodule=pairs)
    logged = trainer.callback_metrics
    assert logged["train/flow_frozen"] == 0.0  # the second step's, after the warm-up
    assert torch.isfinite(logged["train/flow_loss"]) and logged["train/flow_loss"] > 0
    assert logged["train/flow_lr"] == pytest.approx(5e-5)


@pytest.mark.parametrize("find_unused", [False, True])
def test_a_frozen_warm_up_under_ddp_needs_unused_parameters_found(find_unused: bool) -> None:
    """Two DDP processes that do not look for unused parameters would fail at the warm-up's
    second step (the flow network has no gradient): the module's setup, which runs before the
    strategy wraps it, names the setting instead. The Trainer is built, not launched."""
    import lightning as L
    from lightning.pytorch.strategies import DDPStrategy

    trainer = L.Trainer(accelerator="cpu", devices=2, logger=False,
                        strategy=DDPStrategy(find_unused_parameters=find_unused))  # fmt: skip
    for freeze in (0, 3):
        module = _module(freeze_flow_steps=freeze)
        module.trainer = trainer
        if freeze and not find_unused:
            with pytest.raises(ValueError, match="find_unused_parameters=true"):
                module.setup("fit")
        else:
            module.setup("fit")


@pytest.mark.slow
def test_the_experiment_runs_and_predict_reads_its_checkpoints_flow_network(
    tmp_path: Path,
) -> None:
    """The issue's command on a fresh cache, then images → poses with the checkpoint."""
    run = tmp_path / "run"
    run_module("mfg_lightning.train", "experiment=end_to_end", "debug=tiny",
               "model.freeze_flow_steps=2", "logger=none", f"hydra.run.dir={run}",
               cwd=tmp_path)  # fmt: skip
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert np.isfinite(metrics["test/flow_epe"]) and np.isfinite(metrics["test/ate"])
    ckpt = run / "checkpoints" / "last.ckpt"
    out = tmp_path / "predict"
    run_module("mfg_lightning.predict", f"ckpt_path={ckpt}", "dataset=synthetic", "flow=learned",
               f"flow.height={IMAGE_HW[0]}", f"flow.width={IMAGE_HW[1]}",
               f"dataset.height={MODEL_HW[0]}", f"dataset.width={MODEL_HW[1]}",
               "dataset.test_sequences=1", "dataset.sequence_length=8",
               f"hydra.run.dir={out}", cwd=tmp_path)  # fmt: skip
    assert json.loads((out / "predict.json").read_text())["sequences"]
    key = json.loads(next((tmp_path / "cache" / "synthetic_flow").glob("*/meta.json")).read_text())
    assert key["flow"]["estimator"] == "learned"  # the checkpoint's network, by its digest


@pytest.mark.slow
def test_two_ddp_processes_train_end_to_end_after_a_frozen_warm_up(tmp_path: Path) -> None:
    """``trainer=ddp`` (2 CPU processes) with the frozen warm-up and the setting it needs: the
    run finishes, the network past its warm-up leaves the shipped weights in every tensor, one
    kernel set is logged for both processes, and Lightning's ``sync_dist`` advice, wrong for
    values the evaluation has already gathered, is not printed."""
    from mfg_lightning.flow.learned import DEFAULT_WEIGHTS, load_weights

    run = tmp_path / "run"
    proc = run_module("mfg_lightning.train", "experiment=end_to_end", "debug=tiny",
                      "trainer=ddp", "trainer.strategy.find_unused_parameters=true",
                      "model.freeze_flow_steps=2", "trainer.max_steps=6", "logger=none",
                      f"hydra.run.dir={run}", cwd=tmp_path, timeout=600)  # fmt: skip
    out = proc.stdout + proc.stderr
    assert "sync_dist=True" not in out
    assert out.count("kernels of all 2 processes") == 1, out[-3000:]
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 6
    shipped = load_weights(DEFAULT_WEIGHTS)[0].state_dict()
    trained = {k.removeprefix(ckpt["flow_net_prefix"]): v for k, v in ckpt["state_dict"].items()
               if k.startswith(ckpt["flow_net_prefix"])}  # fmt: skip
    assert trained.keys() == shipped.keys()
    unchanged = [k for k, v in shipped.items() if torch.equal(v, trained[k])]
    assert not unchanged, unchanged
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert np.isfinite(metrics["test/flow_epe"]) and np.isfinite(metrics["test/ate"])
