"""flow=learned: the PWC-Net-design network, its weight files, its training on rendered pairs
(python -m mfg_lightning.train_flow) and its use as MFG's flow estimator."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import bench_module, quiet_trainer, run_module
from mfg_lightning.data.flow_pairs import FlowPairsDataModule, FlowPairsDataset
from mfg_lightning.flow.estimators import EstimatedFlow, parse_flow
from mfg_lightning.flow.learned import (
    DEFAULT_WEIGHTS,
    load_weights,
    save_weights,
)
from mfg_lightning.flow.pwc import PWCConfig, PWCFlowNet, correlation, warp
from mfg_lightning.models.flow_module import FlowLitModule, downsample_flow

#: A network small enough for seconds-long tests (the shipped one: conf/model/pwc_flow.yaml)
SMALL = PWCConfig(pyramid=(8, 8, 12, 16), decoder=(16, 16), context=(8, 8), dilations=(1, 2))


# -- the network's parts, against slow direct computations --------------------------------------


def test_the_cost_volume_is_the_channel_mean_of_products_at_every_displacement() -> None:
    gen = torch.Generator().manual_seed(0)
    f0, f1 = torch.randn(2, 3, 5, 6, 7, generator=gen)
    r = 2
    out = correlation(f0, f1, r)
    assert out.shape == (3, 25, 6, 7)
    slow = torch.zeros_like(out)
    for b in range(3):
        for k, (dy, dx) in enumerate(
            (dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)
        ):
            for y in range(6):
                for x in range(7):
                    if 0 <= y + dy < 6 and 0 <= x + dx < 7:
                        slow[b, k, y, x] = (f0[b, :, y, x] * f1[b, :, y + dy, x + dx]).mean()
    torch.testing.assert_close(out, slow, atol=1e-6, rtol=1e-5)


def test_warping_by_a_whole_pixel_flow_reads_the_shifted_pixel_and_zero_outside() -> None:
    features = torch.arange(2 * 4 * 5, dtype=torch.float32).view(1, 2, 4, 5)
    flow = torch.zeros(1, 2, 4, 5)
    torch.testing.assert_close(warp(features, flow), features)
    flow[:, 0] = 1.0  # read one pixel to the right
    shifted = warp(features, flow)
    torch.testing.assert_close(shifted[..., :-1], features[..., 1:])
    assert (shifted[..., -1] == 0).all()
    flow[:, 0], flow[:, 1] = 0.0, -0.5  # half a pixel up: the mean of two rows
    torch.testing.assert_close(
        warp(features, flow)[..., 1:, :], 0.5 * (features[..., 1:, :] + features[..., :-1, :])
    )


def test_the_network_gives_every_level_and_the_input_size_for_any_image_size() -> None:
    net = PWCFlowNet(SMALL).eval()
    a, b = torch.rand(2, 2, 3, 64, 96)
    flows = net(a, b)
    assert [f.shape[-2:] for f in flows] == [(4, 6), (8, 12), (16, 24)]
    odd = net.estimate(a[..., :50, :70], b[..., :50, :70])
    assert odd.shape == (2, 2, 50, 70) and torch.isfinite(odd).all()


def test_block_means_of_the_exact_flow_skip_unknown_vectors() -> None:
    flow = torch.tensor([[1.0, 3.0], [float("nan"), 5.0]]).expand(1, 2, 2, 2).clone()
    flow[:, :, 1, 0] = float("nan")
    mean, known = downsample_flow(flow, 2)
    torch.testing.assert_close(mean, torch.full((1, 2, 1, 1), 3.0))
    assert known.all()
    mean, known = downsample_flow(torch.full((1, 2, 2, 2), float("nan")), 2)
    assert not known.any() and (mean == 0).all()


# -- weight files ------------------------------------------------------------------------------


def test_a_weight_file_round_trips_and_a_wrong_file_is_a_clear_error(tmp_path: Path) -> None:
    net = PWCFlowNet(SMALL)
    path = save_weights(tmp_path / "net.pt", net, {"command": "test"})
    loaded, provenance = load_weights(path)
    assert provenance == {"command": "test"} and loaded.config == SMALL
    for k, v in net.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[k], v)

    text = tmp_path / "notes.txt"
    text.write_text("not weights\n")
    with pytest.raises(ValueError, match=r"flow.weights=.*notes.txt: not a torch file"):
        load_weights(text)
    other = tmp_path / "other.pt"
    torch.save({"state_dict": {"encoder.weight": torch.zeros(1)}}, other)
    with pytest.raises(ValueError, match=r"other.pt: not a flow-network file \(an MFG checkpoint"):
        load_weights(other)
    bigger = PWCFlowNet(PWCConfig(**{**SMALL.to_dict(), "decoder": (16, 16, 16)}))
    mixed = save_weights(tmp_path / "mixed.pt", bigger)
    data = torch.load(mixed, weights_only=True)
    data["config"] = SMALL.to_dict()  # weights of another shape than the config says
    torch.save(data, mixed)
    with pytest.raises(ValueError, match=r"mixed.pt: its weights do not fit the network"):
        load_weights(mixed)
    with pytest.raises(FileNotFoundError, match="flow.weights: no such file"):
        parse_flow({"source": "learned", "weights": str(tmp_path / "absent.pt")}, "exact")


def test_the_estimator_keys_its_cache_by_the_weights_and_estimates_at_the_image_size(
    tmp_path: Path,
) -> None:
    one = save_weights(tmp_path / "one.pt", PWCFlowNet(SMALL))
    torch.manual_seed(1)
    two = save_weights(tmp_path / "two.pt", PWCFlowNet(SMALL))
    flow = parse_flow({"source": "learned", "weights": str(one), "device": "cpu"}, "exact")
    assert isinstance(flow, EstimatedFlow) and flow.source == "learned"
    other = parse_flow({"source": "learned", "weights": str(two)}, "exact")
    assert flow.key() != other.key()
    rgb = np.random.default_rng(0).integers(0, 256, (70, 100, 3), dtype=np.uint8)
    est = flow.estimator(flow.estimator.prepare(rgb), flow.estimator.prepare(rgb))
    assert est.shape == (70, 100, 2) and est.dtype == np.float32 and np.isfinite(est).all()


def test_the_shipped_weights_load_with_their_provenance() -> None:
    net, provenance = load_weights(DEFAULT_WEIGHTS)
    assert net.config == PWCConfig()  # conf/model/pwc_flow.yaml's network
    for key in ("command", "commit", "global_step", "data", "train_seconds", "cpu_kind"):
        assert provenance.get(key) is not None, key
    assert "train_flow" in provenance["command"]
    assert provenance["data"]["trajectory"] == "kitti"
    assert all(int(s) <= 8 for s in provenance["data"]["train_sequences"])  # never 09, 10
    text = json.dumps(provenance)
    assert "/work/" not in text and "/root/" not in text  # no path of the training machine


# -- training ----------------------------------------------------------------------------------


def _tiny_pairs(tmp_path: Path, **kw) -> FlowPairsDataModule:
    settings = dict(
        train_sequences=1, sequence_length=16, val_fraction=0.25, frame_stride=1, val_every=1,
        image_hw=(64, 128), batch_size=4, eval_batch_size=8, num_workers=0, prepare_workers=0,
        cache_dir=str(tmp_path / "cache"),
    )  # fmt: skip
    return FlowPairsDataModule(**{**settings, **kw})


def _val_epe(module: FlowLitModule, data: FlowPairsDataModule) -> float:
    trainer = quiet_trainer()
    return float(trainer.validate(module, datamodule=data, verbose=False)[0]["val/epe"])


def _epe_with_second_frames_of_other_pairs(
    net: PWCFlowNet, dataset: FlowPairsDataset
) -> tuple[float, ...]:
    """The mean end-point errors (px) of ``net`` on the pairs, on the pairs with each second
    frame another pair's, and of zero flow. A network that reads the images gets worse with the
    wrong frames; one that ignores them (a single mean flow for every pair, what a cost volume
    too weak to read led to) scores as on the true pairs."""
    pairs = [dataset[i] for i in range(len(dataset))]
    image0 = torch.stack([p["image0"] for p in pairs]).float() / 255
    image1 = torch.stack([p["image1"] for p in pairs]).float() / 255
    target = torch.stack([p["flow"] for p in pairs])
    known = torch.isfinite(target).all(1)
    with torch.no_grad():
        true = net.estimate(image0, image1)
        other = net.estimate(image0, image1.roll(1, dims=0))
    zero = torch.zeros_like(true)
    err = [(f - torch.nan_to_num(target)).norm(dim=1)[known].mean().item()
           for f in (true, other, zero)]  # fmt: skip
    return tuple(err)


def _pairs_batch(n: int = 4, hw: tuple[int, int] = (64, 128)) -> dict:
    gen = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (2, n, 3, *hw), generator=gen, dtype=torch.uint8)
    flow = torch.randn(n, 2, *hw, generator=gen)
    return {"image0": images[0], "image1": images[1], "flow": flow,
            "sample_id": [f"flow_pairs/00/{i}->{i + 1}" for i in range(n)]}  # fmt: skip


def test_the_augmentation_draws_from_its_step_and_rank_never_from_the_global_generator() -> None:
    """What makes a resumed train_flow draw the crops and flips of the uninterrupted run
    (tests/test_flow_faults.py): each batch's generator is derived from (seed, rank, step,
    batch index), which the checkpoint restores, and torch's global generator is left alone."""
    module = FlowLitModule(net=SMALL.to_dict(), level_weights=(1.0, 1.0, 1.0), crop=(32, 64))
    batch = _pairs_batch()
    torch.manual_seed(0)
    before = torch.get_rng_state()
    first = module._augmented(batch, module.augmentation_generator(3))
    assert torch.equal(torch.get_rng_state(), before)
    again = module._augmented(batch, module.augmentation_generator(3))
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    assert first[0].shape[-2:] == (32, 64)

    def draws(m: FlowLitModule, batch_idx: int) -> torch.Tensor:
        return torch.rand(8, generator=m.augmentation_generator(batch_idx))

    other_seed = FlowLitModule(net=SMALL.to_dict(), level_weights=(1.0, 1.0, 1.0), seed=1)
    rank_0 = draws(module, 3)
    assert not torch.equal(rank_0, draws(module, 4))  # another batch
    assert not torch.equal(rank_0, draws(other_seed, 3))  # another run's seed
    module._trainer = SimpleNamespace(global_rank=1, global_step=0)  # the same step on rank 1
    try:
        assert not torch.equal(rank_0, draws(module, 3))
    finally:
        module._trainer = None


def test_a_non_finite_flow_loss_skips_the_step_and_too_many_stop_the_run() -> None:
    """The run's ``AgreedSteps`` handles the flow module's faults as MFG's: a non-finite loss
    skips the optimiser step (its gradients dropped: the weights stay), and a run of them stops
    at the module's ``max_consecutive_nonfinite``."""
    from mfg_lightning.run.agreed_steps import AgreedSteps, NonFiniteLossError

    module = FlowLitModule(net=SMALL.to_dict(), level_weights=(1.0, 1.0, 1.0),
                           max_consecutive_nonfinite=2)  # fmt: skip
    steps = AgreedSteps()
    steps.setup(None, module, "fit")  # type: ignore[arg-type]
    trainer = SimpleNamespace(world_size=1, training=True, global_step=0)
    optimizer = torch.optim.Adam(module.parameters())
    batch = _pairs_batch(2)
    with torch.no_grad():
        next(module.net.parameters()).fill_(float("nan"))  # the loss is not finite
    before = [p.detach().clone() for p in module.parameters()]

    def step(batch_idx: int) -> None:
        steps.on_train_batch_start(trainer, module, batch, batch_idx)
        loss = module.training_step(batch, batch_idx)
        steps.on_before_backward(trainer, module, loss)
        loss.backward()
        steps.on_before_optimizer_step(trainer, module, optimizer)
        optimizer.step()

    step(0)
    after = [p.detach().nan_to_num() for p in module.parameters()]
    assert all(torch.equal(p, q.nan_to_num()) for p, q in zip(after, before, strict=True))
    with pytest.raises(NonFiniteLossError, match="2 consecutive non-finite losses"):
        step(1)


@pytest.mark.slow
def test_the_shipped_network_reads_both_frames_of_an_unseen_world(tmp_path: Path) -> None:
    """On a procedural world it never saw (the shipped weights were trained on the KITTI
    worlds): far below zero flow, and far worse when each pair's second frame is another's."""
    data = _tiny_pairs(tmp_path, image_hw=(192, 512), sequence_length=14, frame_stride=6,
                       val_fraction=0.1, offsets=(-1, 1))  # fmt: skip
    data.prepare_data()
    net, _ = load_weights(DEFAULT_WEIGHTS)
    true, other, zero = _epe_with_second_frames_of_other_pairs(net, data.dataset("train"))
    assert true < 0.5 * zero and other > 2 * true, (true, other, zero)


@pytest.mark.slow
def test_training_the_flow_network_on_a_tiny_world_lowers_its_end_point_error(
    tmp_path: Path,
) -> None:
    data = _tiny_pairs(tmp_path)
    data.prepare_data()
    assert data.dataset("train").samples and data.dataset("val").samples
    train_frames = {s[1] for s in data.dataset("train").samples}
    assert train_frames.isdisjoint({s[1] for s in data.dataset("val").samples})
    torch.manual_seed(0)
    module = FlowLitModule(
        net=SMALL.to_dict(),
        optimizer=lambda params: torch.optim.Adam(params, lr=2e-3),
        level_weights=(1.0, 1.0, 1.0),
    )
    before = _val_epe(module, data)
    quiet_trainer(max_steps=200, limit_val_batches=0).fit(module, datamodule=data)
    after = _val_epe(module, data)
    assert after < 0.7 * before, (before, after)


@pytest.mark.slow
def test_train_flow_runs_in_a_run_directory_exports_its_network_and_resumes(
    tmp_path: Path,
) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    args = (
        "dataset.train_sequences=1", "dataset.sequence_length=16", "dataset.val_fraction=0.25",
        "dataset.frame_stride=2", "dataset.val_every=2", "dataset.image_hw=[64,128]",
        "dataset.batch_size=2", "dataset.num_workers=0", "dataset.prepare_workers=0",
        "model.net.pyramid=[8,8,12,16]", "model.net.decoder=[16,16]", "model.net.context=[8,8]",
        "model.net.dilations=[1,2]", "model.level_weights=[1,1,1]",
        "trainer.val_check_interval=2", "model.image_log_every_n_steps=2",
        f"hydra.run.dir={run}",
    )  # fmt: skip
    run_module("mfg_lightning.train_flow", *args, "trainer.max_steps=2", cwd=tmp_path)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["metrics"]["val/epe"] > 0 and "val/epe_+1" in metrics["metrics"]
    net, provenance = load_weights(run / "flow_net.pt")
    assert provenance["global_step"] == 2 and net.config.pyramid == (8, 8, 12, 16)
    assert provenance["data"]["cache_dir"] == "<cache_dir>"
    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"images": 0})
    events.Reload()
    assert {"train/flow", "val/flow"} <= set(events.Tags()["images"])
    assert "val/epe" in events.Tags()["scalars"]

    run_module(
        "mfg_lightning.train_flow", *args, "trainer.max_steps=4", "resume=true", cwd=tmp_path
    )
    info = json.loads((run / "run_info.json").read_text())
    assert info["resumed_from"].endswith("last.ckpt")
    _, provenance = load_weights(run / "flow_net.pt")
    assert provenance["global_step"] == 4
    # a train_flow checkpoint is a weight file too
    assert load_weights(run / "checkpoints" / "last.ckpt")[1]["global_step"] == 4

    # bench/flow_training.py: the run's validation curve, kept as JSON, as a section and figure
    bench = bench_module("flow_training")
    out = tmp_path / "results"
    path = bench.main(["--run", str(run), "--work", str(out / "work"), "--out", str(out),
                       "--dis-val-epe", "5.66"])  # fmt: skip
    section = path.read_text().split("<!-- flow-training:start -->")[1]
    rows = [r for r in section.splitlines() if r.startswith("| ") and r[2].isdigit()]
    steps = [int(r.split("|")[1]) for r in rows]  # the two validations, one per run
    assert len(steps) == 2 and 0 < steps[0] < steps[1] <= 4, steps
    assert (out / "flow_quality" / "learned_training.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((out / "work" / "curve.json").read_text())["curve"][0]["step"] == steps[0]


@pytest.mark.slow
def test_mfg_trains_on_the_shipped_learned_flow_out_of_the_box(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run_module(
        "mfg_lightning.train", "flow=learned", "flow.height=64", "flow.width=128",
        "dataset.train_sequences=1", "dataset.test_sequences=1", "dataset.sequence_length=12",
        "dataset.val_fraction=0.3",
        "dataset.batch_size=2", "dataset.eval_batch_size=4", "model.net.hidden_units=64",
        "model.net.channels=[8,8,16,16,32]", "trainer.max_steps=2",
        "trainer.val_check_interval=1", "logger=none", "callbacks=none",
        f"hydra.run.dir={run}", cwd=tmp_path,
    )  # fmt: skip
    assert json.loads((run / "metrics.json").read_text())["metrics"]["test/ate"] is not None
    meta = next((tmp_path / "cache" / "synthetic_flow").glob("*/meta.json"))
    key = json.loads(meta.read_text())["flow"]
    assert key["estimator"] == "learned" and len(key["weights_sha256"]) == 64


@pytest.mark.slow
def test_train_flow_under_ddp_scores_each_validation_pair_once(tmp_path: Path) -> None:
    """``trainer=ddp`` (2 gloo processes): the validation EPE the run logs is the one a single
    process computes with the exported network on the same pairs. The split has an odd number
    of pairs, so torch's padding sampler would count one twice on the second process."""
    run = tmp_path / "run"
    data = dict(
        train_sequences=1, sequence_length=16, val_fraction=0.25, frame_stride=2, val_every=1,
        image_hw=(64, 128), batch_size=2, eval_batch_size=2, num_workers=0, prepare_workers=0,
        cache_dir=str(tmp_path / "cache"), offsets=(-1, 1, 2),
    )  # fmt: skip
    pairs = _tiny_pairs(tmp_path, **data)
    pairs.prepare_data()
    n_val = len(pairs.dataset("val"))
    assert n_val % 2 == 1, n_val
    run_module(
        "mfg_lightning.train_flow", "trainer=ddp", "logger=none",
        *(f"dataset.{k}={json.dumps(list(v) if isinstance(v, tuple) else v)}"
          for k, v in data.items() if k != "cache_dir"),
        f"paths.cache_dir={tmp_path / 'cache'}",
        "model.net.pyramid=[8,8,12,16]", "model.net.decoder=[16,16]", "model.net.context=[8,8]",
        "model.net.dilations=[1,2]", "model.level_weights=[1,1,1]",
        "trainer.max_steps=2", "trainer.val_check_interval=2", f"hydra.run.dir={run}",
        cwd=tmp_path, timeout=300,
    )  # fmt: skip
    logged = json.loads((run / "metrics.json").read_text())["metrics"]
    net, provenance = load_weights(run / "flow_net.pt")
    assert provenance["global_step"] == 2
    module = FlowLitModule(net=net.config.to_dict(), level_weights=(1.0, 1.0, 1.0))
    module.net.load_state_dict(net.state_dict())
    single = quiet_trainer().validate(module, datamodule=pairs, verbose=False)[0]
    for key in ("val/epe", "val/fl", "val/epe_+1", "val/epe_+2", "val/epe_-1"):
        assert logged[key] == pytest.approx(single[key], rel=1e-5), key
