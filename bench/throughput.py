"""Question 2: how fast does MFG train and infer, what does the framework cost, what does
bf16-mixed buy, and does the data keep up?

Measured in one run, on the same MFG (the quick-start config: 48 × 128 flow, M = 1000, fused
Adam), the same samples already in memory (pre-collated batches, cycled) and batch 1, 16 and 32:

0. the machine's 2048² GEMM peak in float32 and bfloat16, and the network's FLOPs per sample
   (forward + backward, ``torch.utils.flop_counter.FlopCounterMode``).
1. training samples per second under ``32-true`` and ``bf16-mixed``, through the Lightning
   Trainer (``MFGLitModule.training_step``) and a bare PyTorch loop written here (the same
   fields, forward, loss, backward and optimiser step; bf16: the encoder under CPU autocast, the
   decoders in float32, as the module runs it), all four interleaved; Lightning / bare (target
   ≥ 0.95×), bf16 / float32 (target ≥ 2.2× at batch 32, ≥ 1.8× at 16), each rate as a
   fraction of its own dtype's GEMM peak.
2. inference from flow to (t, ω) (``predict_motion``) against the bare forward. Target ≤ +10 %.
3. loader-only samples per second (the exact-flow generator in the training process and in one
   DataLoader worker; cached rendered DIS flow) and training on the real loader at each
   precision: how much of the step waits on data.
4. the peak resident memory of a real training run (``python -m mfg_lightning.train``), and the
   page faults a training step takes with the C library's default against freed memory kept
   (what every training run does, :mod:`mfg_lightning.core.host_memory`).
5. where the step's time goes: ``torch.profiler`` per operator under both precisions, every
   convolution and decoder alone (GFLOP/s, fraction of peak), and what caps bf16-mixed.
6. the candidate speed-ups in the bare loop: fused Adam (adopted), channels-last, the first
   convolution (2 input channels) in float32 or padded to 8 channels, ``torch.compile``.
7. the convolutions' implementations (``model.net.conv_impl``, :mod:`mfg_lightning.models.conv`):
   each layer's forward + backward as native / im2col / channels-last at the training batch, in
   float32 (and bfloat16 under autocast where the CPU has it natively), the one ``auto`` picks,
   and the training step with ``auto``'s choice against native (bare loop, interleaved). Written
   as its own section of throughput.md; ``--convolutions`` runs only it (about a minute).

Every rate is the median of ``--repeats`` interleaved measurements, each over ``--steps-*``
steps after a warm-up: the machine may be shared.

The sample cache (``dataset.sample_cache``, ``dataset.prefetch``), a section of its own:
the loader alone and training on it in the first epoch (samples computed, with each
prefetch) and the second (read back), against the uncached generator and the same batches
held in memory; ``--sample-cache`` runs only it (about 4 minutes). ``--quick-start`` runs only the
quick start, without and with the cache (about 10 minutes), in a section per instruction set
torch's kernels use: ``ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2
MKL_ENABLE_INSTRUCTIONS=AVX2`` before it imitates an AVX2 machine on an AVX-512 one.

``python bench/throughput.py`` (about 8 minutes on 2 CPU cores); ``--tiny`` for a smoke run;
``python bench/throughput.py --convolutions`` for section 7 alone.

Each section is a module of ``bench/throughput_sections/``; this script parses the command line
and runs them in order.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_common_arguments
from throughput_sections import (
    candidates,
    convolutions,
    gemm_peak,
    inference,
    lightning_vs_bare,
    loader,
    memory,
    profiles,
    quick_start,
    sample_cache,
)
from throughput_sections.measure import (
    Run,
    base_overrides,
    build_model,
    render,
    throughput_report,
)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16, 32])
    p.add_argument("--samples", type=int, default=256, help="samples held in memory")
    p.add_argument("--steps-per-batch-size", type=int, nargs="+", default=[200, 40, 24])
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--repeats", type=int, default=5, help="of the Lightning/bare comparison")
    p.add_argument("--candidate-repeats", type=int, default=2, help="of the other measurements")
    p.add_argument("--rss-steps", type=int, default=60, help="steps of the peak-memory run")
    p.add_argument("--no-compile", action="store_true", help="skip the torch.compile candidate")
    p.add_argument(
        "--convolutions", action="store_true", help="only the convolution implementations (7.)"
    )
    p.add_argument("--conv-repeats", type=int, default=5, help="timed repeats per layer (7.)")
    p.add_argument("--conv-steps", type=int, default=20, help="training steps per rate (7.)")
    p.add_argument("--sample-cache", action="store_true", help="only the sample cache")
    p.add_argument(
        "--quick-start", action="store_true",
        help="only the quick start, without and with the sample cache (a section per "
        "instruction set torch's kernels use)",
    )  # fmt: skip
    p.add_argument("--cache-frames", type=int, default=200,
                   help="frames of each of the 2 training trajectories (sample cache)")  # fmt: skip
    p.add_argument("--cache-epochs", type=int, default=3,
                   help="epochs of each training (sample cache): the first computes the "
                   "samples, the later ones, timed together, read them back")  # fmt: skip
    add_common_arguments(p)
    return p.parse_args(argv)


def tiny(args: argparse.Namespace) -> None:
    """``--tiny``: the sizes, steps and repeats of a seconds-long smoke run, in place."""
    args.samples, args.steps_per_batch_size = 8, [4, 2, 2]
    args.batch_sizes, args.warmup, args.rss_steps = [1, 2, 4], 2, 2
    args.repeats = args.candidate_repeats = 1
    args.no_compile = True
    args.conv_repeats, args.conv_steps = 1, 2


def main(argv: list[str] | None = None) -> Path:
    """Run the sections the command line asks for; returns the path of throughput.md."""
    args = parse_args(argv)
    if args.tiny:
        tiny(args)
    if len(args.steps_per_batch_size) != len(args.batch_sizes):
        raise SystemExit("error: give one --steps-per-batch-size per --batch-sizes")
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    # as every training run does (mfg_lightning.core.host_memory): freed tensors' memory reused
    # in this process, by the Lightning and the bare loops alike
    from mfg_lightning.core.host_memory import keep_freed_memory

    keep_freed_memory()
    if args.quick_start:  # (subprocesses: no model built here)
        return quick_start.section(args)
    base = base_overrides(args.tiny)
    _, cfg = build_model(base)
    if args.sample_cache:
        return sample_cache.section(args, cfg)
    if args.convolutions:
        return convolutions.section(args, base, cfg)
    report = throughput_report(args.out)  # (its wall time counts the rendering too)
    samples = render(cfg, max(args.samples, *args.batch_sizes))
    run = Run(args, base, cfg, samples, report)
    run.report.add(
        f"MFG {cfg.dataset.height} × {cfg.dataset.width}, M = {cfg.model.net.hidden_units}, "
        f"channels {list(cfg.model.net.channels)}, fused Adam (the default); {args.samples} "
        f"synthetic samples in memory, pre-collated; rates are medians of {args.repeats} "
        f"(Lightning/bare) or {args.candidate_repeats} (candidates) interleaved runs, each "
        f"{args.warmup} warm-up steps then {args.steps_per_batch_size} steps (per batch size "
        f"{args.batch_sizes}); a run's rate is the batch over its median step time (a step "
        "that another process stalled does not count)."
    )
    peaks = gemm_peak.section(run)
    rates = lightning_vs_bare.section(run, peaks)
    inference.section(run)
    loader.section(run)
    memory.section(run)
    memory.host_memory_section(run)
    profiles.section(run, peaks, rates)
    candidates.section(run)
    run.report.write()
    # 7. and the sample cache: sections of their own (--convolutions, --sample-cache rerun them).
    path = convolutions.section(args, base, cfg, samples)
    sample_cache.section(args, cfg)
    return path


if __name__ == "__main__":
    main()
