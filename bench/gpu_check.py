"""Does the GPU path run? Train, check determinism, evaluate on both devices (issues 22, 35).

``make gpu-check`` installs what is missing (``make install-gpu``) and runs this script; on one
CUDA device it takes a few minutes. The parts, in order:

0. Preparation. ``CUBLAS_WORKSPACE_CONFIG`` is set first (cuBLAS reads it when it creates its
   handle, which Part 1 does; Lightning sets it only when a deterministic Trainer is built, too
   late for Part 2). ``/dev/shm`` is checked against what the loader workers keep in flight
   (workers × prefetch × (train + evaluation batch) × the measured bytes of a sample; Docker's
   default ``/dev/shm`` is 64 MB): when it is too small the workers are reduced to fit and the
   report says what to change to keep them.
1. Training: the quick-start setting (``python -m mfg_lightning.train trainer=gpu``: synthetic
   exact flow at 48 × 128, batch 16, the default network) for ``--steps`` steps under each of
   ``--precisions``, through the Trainer a run builds (:func:`mfg_lightning.run.runs.build_trainer`,
   ``trainer=gpu``'s loader workers, pinned memory and cuDNN benchmark). Three rates, in
   samples/s over the steps after ``--warmup``: training on the real loader; training on cached
   batches (collated once, pinned, cycled: the device side alone, the copy to the device
   included); and the loader alone (its batches iterated, nothing trained). The smaller of the
   last two limits the first.
2. Determinism: ``--det-steps`` steps under ``trainer.deterministic=true`` twice from the same
   seed; the weights must come out bit for bit the same (the deterministic upsampling and
   ``CUBLAS_WORKSPACE_CONFIG``; README, "Precision and the GPU").
3. Evaluation: one checkpoint (the ``32-true`` run's, or the first precision's when
   ``32-true`` is not among ``--precisions``) tested on the CPU in float32 and on the device under
   each precision, the path ``evaluate trainer=gpu`` runs (no deterministic algorithms, cuDNN
   benchmark on). Every compared metric must agree with the CPU's within its tolerance,
   :data:`TOLERANCE`, whose basis :data:`TOLERANCE_BASIS` states.

torch's process-wide settings (deterministic algorithms, cuDNN benchmark and deterministic) are
put back as they were before each part, so that no part runs in a state an earlier one left
(Part 2's ``use_deterministic_algorithms(True)`` would otherwise send Part 3 down the
matrix-product upsampling, not the path a user's evaluation takes); the report lists them at the
start of each part.

``python bench/gpu_check.py`` on a machine with a CUDA GPU writes ``bench/results/gpu_check.md``;
``--tiny --accelerator cpu`` is the test suite's seconds-long run of the same code on a CPU
(``make gpu-check GPU_CHECK_ACCELERATOR=cpu GPU_CHECK_ARGS=--tiny``, tests/test_gpu_path.py),
whose numbers mean nothing. Part 0's process-wide state is ``bench/gpu_check_parts/state.py``.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate

from mfg_lightning.data.workers import plan_workers, sample_bytes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import TINY_OVERRIDES, Report, add_common_arguments, fmt, markdown_table
from gpu_check_parts.state import flags_restored, set_cublas_workspace

#: The test metrics compared between the devices.
COMPARED = ("test/ate", "test/rpe_trans", "test/rpe_rot", "test/trans_err", "test/rot_err")
#: Relative tolerance of each evaluation against the CPU's float32 one.
TOLERANCE = {"32-true": 0.00015, "bf16-mixed": 0.011, "16-mixed": 0.01}
#: Why each tolerance is what it is: about 3× the largest relative difference the first GPU run
#: measured on the default network (bench/results/gpu_check.md, NVIDIA H200, torch 2.11.0+cu130,
#: 2026-12-04), so that a rerun's noise passes and a broken path does not.
TOLERANCE_BASIS = {
    "32-true": (
        "3x the first GPU run's largest difference (0.005 %, NVIDIA H200, "
        "bench/results/gpu_check.md): TF32 convolutions moved the test metrics that little"
    ),
    "bf16-mixed": (
        "3x the first GPU run's largest difference (0.369 %, test/rpe_trans and trans_err, "
        "NVIDIA H200, bench/results/gpu_check.md): the encoder alone in bfloat16"
    ),
    "16-mixed": "provisional, not measured on a GPU yet: as bf16-mixed, float16's encoder",
}
#: ``--tiny``: a seconds-long run (the tiny model on a tiny synthetic set).
TINY_DATA = (
    "dataset.batch_size=4",
    "dataset.eval_batch_size=8",
    "dataset.train_sequences=1",
    "dataset.test_sequences=1",
    "dataset.sequence_length=16",
    "dataset.val_fraction=0.2",
    "dataset.num_workers=0",
    "++dataset.persistent_workers=false",
)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    from mfg_lightning.run.precision import check_precision

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--accelerator", choices=["gpu", "cpu"], default="gpu")
    p.add_argument("--precisions", nargs="+", default=["32-true", "bf16-mixed"])
    p.add_argument("--steps", type=int, default=300, help="training steps per precision")
    p.add_argument("--warmup", type=int, default=20, help="steps left out of samples/s")
    p.add_argument("--det-steps", type=int, default=50, help="steps of each deterministic run")
    p.add_argument("--loader-batches", type=int, default=100, help="batches of the loader alone")
    p.add_argument(
        "--shm", type=Path, default=Path("/dev/shm"), help="the loader workers' shared memory"
    )
    add_common_arguments(p)
    args = p.parse_args(argv)
    try:  # Lightning's aliases (bf16, 32) named as the module names them, each once
        args.precisions = list(dict.fromkeys(check_precision(x) for x in args.precisions))
    except ValueError as err:
        p.error(str(err))
    if args.tiny:
        args.steps, args.warmup, args.det_steps, args.loader_batches = 6, 2, 3, 3
    return args


# --------------------------------------------------------------------------------------------
# Part 1: training rates
# --------------------------------------------------------------------------------------------


class StepTimer(L.Callback):
    """Wall time from the start of step ``warmup`` to the end of training, with the device
    synchronised at both ends (CUDA runs asynchronously)."""

    def __init__(self, warmup: int) -> None:
        self.warmup = warmup
        self.start: float | None = None
        self.first = 0
        self.seconds = math.nan
        self.steps = 0

    @staticmethod
    def _now(pl_module: L.LightningModule) -> float:
        if pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)
        return time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self.start is None and trainer.global_step >= self.warmup:
            self.start, self.first = self._now(pl_module), trainer.global_step

    def on_train_end(self, trainer, pl_module) -> None:
        if self.start is not None:
            self.seconds = self._now(pl_module) - self.start
            self.steps = trainer.global_step - self.first


def config(args: argparse.Namespace, work: Path, *extra: str) -> Any:
    """The train config of the check: the quick start on the chosen device, nothing logged."""
    from mfg_lightning.core.config import compose

    overrides = [
        f"trainer={args.accelerator}",
        "logger=none",
        "callbacks=none",
        f"paths.output_dir={work}",
        f"trainer.max_steps={args.steps}",
        "trainer.limit_val_batches=0",
        f"trainer.log_every_n_steps={max(1, min(50, args.steps))}",
        "trainer.enable_model_summary=false",
        "++trainer.enable_progress_bar=false",
        "model.image_log_every_n_steps=0",
    ]
    if args.tiny:
        overrides += [*TINY_OVERRIDES, *TINY_DATA]
    overrides += list(getattr(args, "loader_overrides", ()))
    return compose("train", [*overrides, *extra])


class CachedBatches(torch.utils.data.Dataset):
    """``length`` items cycling through batches collated once (``DataLoader(batch_size=None)``
    hands them over as they are): training without the generator's cost."""

    def __init__(self, batches: list[dict[str, Any]], length: int) -> None:
        self.batches, self.length = batches, length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int) -> dict[str, Any]:
        return self.batches[i % len(self.batches)]


def cached_loader(cfg: Any, n_batches: int, steps: int) -> torch.utils.data.DataLoader:
    """A loader of ``n_batches`` training batches made once (pinned where CUDA is, as the real
    loader's are), cycled for ``steps`` steps in one epoch."""
    from hydra.utils import instantiate

    datamodule = instantiate(cfg.dataset)
    datamodule.setup("fit")
    batches = []
    for batch in datamodule.train_dataloader():
        if torch.cuda.is_available():
            batch = {k: v.pin_memory() if isinstance(v, torch.Tensor) else v
                     for k, v in batch.items()}  # fmt: skip
        batches.append(batch)
        if len(batches) == n_batches:
            break
    return torch.utils.data.DataLoader(CachedBatches(batches, steps), batch_size=None)


def loader_rate(cfg: Any, n_batches: int) -> float:
    """Samples/s of the configured training loader alone, after its first batch (the workers'
    start left out)."""
    from hydra.utils import instantiate

    datamodule = instantiate(cfg.dataset)
    datamodule.setup("fit")
    loader = iter(datamodule.train_dataloader())
    samples, start = 0, None
    for i in range(n_batches + 1):
        try:
            batch = next(loader)
        except StopIteration:
            loader = iter(datamodule.train_dataloader())
            batch = next(loader)
        if i == 0:
            start = time.perf_counter()
        else:
            samples += len(batch["flow"])
    assert start is not None
    return samples / (time.perf_counter() - start)


def fit(cfg: Any, warmup: int, loader: Any = None) -> tuple[Any, Any, dict[str, float]]:
    """Build the run's datamodule (or take ``loader``), model and Trainer from ``cfg`` and fit;
    the model, the trainer and ``{samples/s, loss, peak GiB}``."""
    from hydra.utils import instantiate

    from mfg_lightning.run.runs import build_model, build_trainer, set_baseline
    from mfg_lightning.run.training import check_trainer_settings

    check_trainer_settings(cfg)
    L.seed_everything(cfg.seed, workers=True)
    data = {"train_dataloaders": loader} if loader is not None else {
        "datamodule": instantiate(cfg.dataset)}  # fmt: skip
    model = build_model(cfg)
    if "datamodule" in data:
        set_baseline(model, data["datamodule"])
    timer = StepTimer(warmup)
    trainer = build_trainer(cfg, [timer], [])
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    trainer.fit(model, **data)
    rate = timer.steps * int(cfg.dataset.batch_size) / timer.seconds if timer.steps else math.nan
    # the strategy's device: Lightning's teardown has moved the model back to the CPU by now
    on_cuda = trainer.strategy.root_device.type == "cuda"
    peak = torch.cuda.max_memory_allocated() / 2**30 if on_cuda else math.nan
    loss = float(trainer.callback_metrics.get("train/loss", math.nan))
    return model, trainer, {"samples/s": rate, "loss": loss, "peak GiB": peak}


def train_each_precision(args: argparse.Namespace, work: Path) -> tuple[str, Path]:
    """Part 1: a table of training rates; the checkpoint Part 3 evaluates."""
    rows, rates, ckpt = [], {}, work / "check.ckpt"
    saved_from = "32-true" if "32-true" in args.precisions else args.precisions[0]
    n_cached = max(1, min(args.steps, 64))
    loader_alone = loader_rate(config(args, work / "loader"), args.loader_batches)
    for precision in args.precisions:
        with flags_restored():
            cfg = config(args, work / precision, f"trainer.precision={precision}")
            _, trainer, res = fit(cfg, args.warmup)
            rates[precision] = res["samples/s"]
            if precision == saved_from:
                trainer.save_checkpoint(ckpt)
        with flags_restored():
            cfg = config(args, work / f"{precision}_cached", f"trainer.precision={precision}")
            _, _, cached = fit(cfg, args.warmup, cached_loader(cfg, n_cached, args.steps))
        real, device = res["samples/s"], cached["samples/s"]
        limit = "loader" if loader_alone < device else "device"
        rows.append([precision, args.steps, fmt(real, 1), fmt(device, 1), fmt(loader_alone, 1),
                     limit, fmt(res["loss"], 1), fmt(res["peak GiB"], 2)])  # fmt: skip
    for row in rows:
        base = rates.get("32-true", math.nan)
        row.append(fmt(rates[row[0]] / base, 2) + "×" if base == base else "-")
    header = ["precision", "steps", "samples/s", "samples/s, cached batches (device side)",
              "samples/s, loader alone", "limited by", "final train/loss", "peak GiB",
              "vs 32-true"]  # fmt: skip
    note = (
        f"\n\nsamples/s: training on the real loader; cached batches: {n_cached} batches "
        "collated once and cycled (the device's own rate, the copy to it included); loader "
        "alone: its batches iterated without training. The smaller of the last two limits the "
        "first. Part 3 evaluates the checkpoint of the "
        f"`{saved_from}` run."
    )
    return markdown_table(header, rows) + note, ckpt


# --------------------------------------------------------------------------------------------
# Parts 2 and 3
# --------------------------------------------------------------------------------------------


def check_determinism(args: argparse.Namespace, work: Path) -> str:
    """Part 2: two deterministic runs from the same seed, weights compared bit for bit."""
    states = []
    for run in ("a", "b"):
        cfg = config(
            args,
            work / f"det_{run}",
            "trainer.deterministic=true",
            f"trainer.max_steps={args.det_steps}",
        )
        model, _, _ = fit(cfg, warmup=0)
        states.append({k: v.detach().cpu() for k, v in model.state_dict().items()})
    diff = max(
        (states[0][k].double() - states[1][k].double()).abs().max().item() for k in states[0]
    )
    same = all(torch.equal(states[0][k], states[1][k]) for k in states[0])
    rows = [[args.det_steps, fmt(diff, 3), "yes" if same else "no"]]
    return markdown_table(["steps", "largest weight difference", "bit-identical"], rows)


def evaluate(ckpt: Path, accelerator: str, precision: str, cfg: Any) -> dict[str, float]:
    """Test the checkpoint on one device under one precision, as ``evaluate trainer=gpu`` does
    (no deterministic algorithms, cuDNN benchmark on a GPU): the ``test/*`` metrics."""
    from hydra.utils import instantiate

    from mfg_lightning.run.checkpoints import module_from_checkpoint

    model = module_from_checkpoint(ckpt)
    trainer = L.Trainer(
        accelerator=accelerator,
        devices=1,
        precision=precision,
        deterministic=False,
        benchmark=accelerator == "gpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.test(model, datamodule=instantiate(cfg.dataset), verbose=False)
    return {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")}


def compare_devices(args: argparse.Namespace, ckpt: Path, work: Path) -> str:
    """Part 3: the checkpoint on the CPU against the device, each metric within tolerance."""
    cfg = config(args, work / "eval")
    runs = {}
    for accelerator, precision in [("cpu", "32-true")] + [
        (args.accelerator, p) for p in args.precisions
    ]:
        with flags_restored():
            runs[(accelerator, precision)] = evaluate(ckpt, accelerator, precision, cfg)
    ref = runs[("cpu", "32-true")]
    header = ["metric", "CPU 32-true"]
    for precision in args.precisions:
        header += [
            f"{args.accelerator} {precision}",
            "rel. diff",
            f"≤ {100 * TOLERANCE[precision]:g} %",
        ]
    rows = []
    for name in COMPARED:
        row = [name, fmt(ref[name], 5)]
        for precision in args.precisions:
            value = runs[(args.accelerator, precision)][name]
            rel = abs(value - ref[name]) / abs(ref[name]) if ref[name] else abs(value)
            ok = "yes" if rel <= TOLERANCE[precision] else "no"
            row += [fmt(value, 5), f"{fmt(100 * rel, 3)} %", ok]
        rows.append(row)
    network = "the tiny network (`--tiny`)" if args.tiny else "the default network"
    basis = "\n".join(
        f"* `{p}` ≤ {100 * TOLERANCE[p]:g} %: {TOLERANCE_BASIS[p]}." for p in args.precisions
    )
    return (
        markdown_table(header, rows)
        + f"\n\nMeasured on {network}. Tolerances and their basis:\n\n{basis}"
    )


def flags_table(flags: dict[str, dict[str, bool]]) -> str:
    names = [k for k in next(iter(flags.values())) if k != "warn only"]
    rows = [[part, *("on" if state[k] else "off" for k in names)] for part, state in flags.items()]
    return markdown_table(["at the start of", *names], rows)


def main(argv: list[str] | None = None) -> Path:
    cublas = set_cublas_workspace()  # before anything can create a cuBLAS handle
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.accelerator == "gpu" and not torch.cuda.is_available():
        raise SystemExit(
            "error: no CUDA device here (torch "
            f"{torch.__version__}, built for CUDA {torch.version.cuda}); `make install-gpu` "
            "says why, docs/gpu.md what to do; --accelerator cpu runs the check on the CPU"
        )
    device = torch.cuda.get_device_name(0) if args.accelerator == "gpu" else "CPU (smoke run)"
    report = Report("gpu_check", "GPU check: training, determinism, evaluation on two devices",
                    args.out)  # fmt: skip
    report.add(f"Device: **{device}**" + (" (`--tiny`: numbers meaningless)" if args.tiny else ""))
    with tempfile.TemporaryDirectory(prefix="mfg-gpu-check-") as tmp:
        work = Path(tmp)
        base = config(args, work / "probe")
        shm = plan_workers(
            int(base.dataset.num_workers),
            int(base.dataset.batch_size),
            int(base.dataset.eval_batch_size),
            sample_bytes(instantiate(base.dataset).dataset("train")[0]),
            args.shm,
        )
        if shm.workers != int(base.dataset.num_workers):
            args.loader_overrides = [f"dataset.num_workers={shm.workers}"]
            if shm.workers == 0:
                args.loader_overrides.append("++dataset.persistent_workers=false")
        report.add(f"## Preparation\n\n* {cublas}\n* {shm.note}")
        flags: dict[str, dict[str, bool]] = {}
        with flags_restored() as flags["Part 1 (training)"]:
            table, ckpt = train_each_precision(args, work)
        report.add("## Training (quick start)\n\n" + table)
        with flags_restored() as flags["Part 2 (determinism)"]:
            det = check_determinism(args, work)
        report.add("## Determinism (`trainer.deterministic=true`, two runs, same seed)\n\n" + det)
        with flags_restored() as flags["Part 3 (evaluation)"]:
            compared = compare_devices(args, ckpt, work)
        report.add(
            "## One checkpoint on the CPU and on the device\n\n"
            "The checkpoint of Part 1, tested on the test split; relative difference to the "
            "CPU's float32 evaluation.\n\n" + compared
        )
        report.add(
            "## torch's settings at the start of each part\n\n"
            "Put back after each part: Lightning's Trainer sets them and never restores them.\n\n"
            + flags_table(flags)
        )
    return report.write()


if __name__ == "__main__":
    main()
