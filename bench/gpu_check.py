"""Does the GPU path run? Train, check determinism, evaluate on both devices (issue 22).

On one CUDA device, in under 5 minutes:

1. Training: the quick-start setting (``python -m mfg_lightning.train trainer=gpu``: synthetic
   exact flow at 48 × 128, batch 16, the default network) for ``--steps`` steps under each of
   ``--precisions`` (``32-true`` and ``bf16-mixed``), through the Trainer a run builds
   (:func:`mfg_lightning.run.runs.build_trainer`, ``trainer=gpu``'s loader workers, pinned memory
   and cuDNN benchmark); samples per second over the steps after ``--warmup``.
2. Determinism: ``--det-steps`` steps under ``trainer.deterministic=true`` twice from the same
   seed; the weights must come out bit for bit the same (the deterministic upsampling and
   Lightning's ``CUBLAS_WORKSPACE_CONFIG``; README, "Precision and the GPU").
3. Evaluation: the ``32-true`` model's checkpoint tested on the CPU (``32-true``) and on the
   device (``32-true`` and ``bf16-mixed``). Every compared metric must agree with the CPU's
   within its tolerance: 0.5 % for the device's ``32-true`` (cuDNN runs float32 convolutions in
   TF32 by default, ~1e-3 relative per product) and 1 % for ``bf16-mixed`` (the issue's bound).

``python bench/gpu_check.py`` on a machine with a CUDA GPU writes ``bench/results/gpu_check.md``;
``--tiny --accelerator cpu`` is the test suite's seconds-long run of the same code on a CPU
(tests/test_precision.py), whose numbers mean nothing.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import TINY_OVERRIDES, Report, add_common_arguments, fmt, markdown_table

#: The test metrics compared between the devices.
COMPARED = ("test/ate", "test/rpe_trans", "test/rpe_rot", "test/trans_err", "test/rot_err")
#: Relative tolerance of each evaluation against the CPU's float32 one.
TOLERANCE = {"32-true": 0.005, "bf16-mixed": 0.01, "16-mixed": 0.01}
#: --tiny: a seconds-long run (the tiny model on a tiny synthetic set).
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
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--accelerator", choices=["gpu", "cpu"], default="gpu")
    p.add_argument("--precisions", nargs="+", default=["32-true", "bf16-mixed"])
    p.add_argument("--steps", type=int, default=300, help="training steps per precision")
    p.add_argument("--warmup", type=int, default=20, help="steps left out of samples/s")
    p.add_argument("--det-steps", type=int, default=50, help="steps of each deterministic run")
    add_common_arguments(p)
    args = p.parse_args(argv)
    if args.tiny:
        args.steps, args.warmup, args.det_steps = 6, 2, 3
    return args


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
    return compose("train", [*overrides, *extra])


def fit(cfg: Any, warmup: int) -> tuple[Any, Any, dict[str, float]]:
    """Build the run's datamodule, model and Trainer from ``cfg`` and fit; the model, the
    trainer and ``{samples/s, loss, peak GiB}``."""
    from hydra.utils import instantiate

    from mfg_lightning.run.runs import build_model, build_trainer
    from mfg_lightning.run.training import check_trainer_settings

    check_trainer_settings(cfg)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = instantiate(cfg.dataset)
    model = build_model(cfg)
    timer = StepTimer(warmup)
    trainer = build_trainer(cfg, [timer], [])
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    trainer.fit(model, datamodule=datamodule)
    rate = timer.steps * int(cfg.dataset.batch_size) / timer.seconds if timer.steps else math.nan
    peak = torch.cuda.max_memory_allocated() / 2**30 if model.device.type == "cuda" else math.nan
    loss = float(trainer.callback_metrics.get("train/loss", math.nan))
    return model, trainer, {"samples/s": rate, "loss": loss, "peak GiB": peak}


def train_each_precision(args: argparse.Namespace, work: Path) -> tuple[str, Path]:
    """Part 1: a table of training rates; the 32-true model's checkpoint."""
    rows, rates, ckpt = [], {}, work / "check.ckpt"
    for precision in args.precisions:
        cfg = config(args, work / precision, f"trainer.precision={precision}")
        _, trainer, res = fit(cfg, args.warmup)
        rates[precision] = res["samples/s"]
        if precision == "32-true":
            trainer.save_checkpoint(ckpt)
        rows.append([precision, args.steps, fmt(res["samples/s"], 1), fmt(res["loss"], 1),
                     fmt(res["peak GiB"], 2)])  # fmt: skip
    for row in rows:
        base = rates.get("32-true", math.nan)
        row.append(fmt(rates[row[0]] / base, 2) + "×" if base == base else "-")
    header = ["precision", "steps", "samples/s", "final train/loss", "peak GiB", "vs 32-true"]
    return markdown_table(header, rows), ckpt


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
    """Test the checkpoint on one device under one precision: the ``test/*`` metrics."""
    from hydra.utils import instantiate

    from mfg_lightning.run.checkpoints import module_from_checkpoint

    model = module_from_checkpoint(ckpt)
    trainer = L.Trainer(
        accelerator=accelerator,
        devices=1,
        precision=precision,
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
    runs = {("cpu", "32-true"): evaluate(ckpt, "cpu", "32-true", cfg)}
    for precision in args.precisions:
        runs[(args.accelerator, precision)] = evaluate(ckpt, args.accelerator, precision, cfg)
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
    return markdown_table(header, rows)


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.accelerator == "gpu" and not torch.cuda.is_available():
        raise SystemExit("error: no CUDA device here; --accelerator cpu runs the check on the CPU")
    device = torch.cuda.get_device_name(0) if args.accelerator == "gpu" else "CPU (smoke run)"
    report = Report("gpu_check", "GPU check: training, determinism, evaluation on two devices",
                    args.out)  # fmt: skip
    report.add(f"Device: **{device}**" + (" (`--tiny`: numbers meaningless)" if args.tiny else ""))
    with tempfile.TemporaryDirectory(prefix="mfg-gpu-check-") as tmp:
        work = Path(tmp)
        table, ckpt = train_each_precision(args, work)
        report.add("## Training (quick start)\n\n" + table)
        report.add(
            "## Determinism (`trainer.deterministic=true`, two runs, same seed)\n\n"
            + check_determinism(args, work)
        )
        report.add(
            "## One checkpoint on the CPU and on the device\n\n"
            "The `32-true` model of the training above, tested on the test split; relative "
            "difference to the CPU's float32 evaluation.\n\n" + compare_devices(args, ckpt, work)
        )
    return report.write()


if __name__ == "__main__":
    main()
