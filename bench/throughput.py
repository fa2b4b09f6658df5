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
4. the peak resident memory of a real training run (``python -m mfg_lightning.train``).
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
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from functools import cache, partial
from pathlib import Path
from typing import Any

import torch

from mfg_lightning.core.machine import isa_caps

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (
    NOISY,
    TINY_OVERRIDES,
    Report,
    add_common_arguments,
    fmt,
    markdown_table,
    ratio_cell,
)

#: The optimiser settings compared: the default build and the faster one.
VARIANTS = {
    "before (for-loop Adam)": ["++model.optimizer.fused=false"],
    "after (fused Adam)": ["++model.optimizer.fused=true"],
}
SAMPLE_KEYS = ("flow", "flow_valid", "pose", "intrinsics", "sequence", "frame", "target")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16, 32])
    p.add_argument("--samples", type=int, default=256, help="samples held in memory")
    p.add_argument("--steps-per-batch-size", type=int, nargs="+", default=[100, 20, 12])
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--repeats", type=int, default=3, help="of the Lightning/bare comparison")
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


def base_overrides(tiny: bool) -> list[str]:
    """The quick-start model (or the tiny test model) with nothing logged per step, on PyTorch's
    own convolutions (section 7 compares the others)."""
    # A constant learning rate: the bare loop has no scheduler, and a scheduler step costs the
    # same in either loop.
    ov = ["paths.output_dir=.", "model.image_log_every_n_steps=0", "model.scheduler=null"]
    # The data rows measure the generator itself (the sample cache has its own section).
    ov += UNCACHED_SAMPLES
    ov += ["model.net.conv_impl=native"]
    if tiny:
        ov += TINY_OVERRIDES
    return ov


@cache
def _config(overrides: tuple[str, ...]):
    """The composed train config (composing is slow; every measurement builds a fresh model)."""
    from mfg_lightning.core.config import compose

    return compose("train", list(overrides))


def build_model(overrides: list[str], seed: int = 0):
    """An ``MFGLitModule`` from the train config with these overrides, seeded."""
    from mfg_lightning.run.runs import build_model as build

    cfg = _config(tuple(overrides))
    torch.manual_seed(seed)
    return build(cfg), cfg


class InMemory:
    """The same pre-collated batches, cycled for ``length`` steps (an iterable Lightning takes
    as a train dataloader without wrapping it in a sampler)."""

    def __init__(self, batches: list[dict], length: int) -> None:
        self.batches, self.length = batches, length

    def __iter__(self) -> Iterator[dict]:
        return (self.batches[i % len(self.batches)] for i in range(self.length))

    def __len__(self) -> int:
        return self.length


def render(cfg, n_samples: int) -> list[dict]:
    """``n_samples`` training samples of the configured synthetic dataset, rendered once."""
    from hydra.utils import instantiate

    dataset = instantiate(cfg.dataset).dataset("train")
    return [{k: dataset[i][k] for k in SAMPLE_KEYS} for i in range(n_samples)]


def make_batches(samples: list[dict], batch_size: int) -> list[dict]:
    """The samples collated into consecutive batches (the remainder is dropped)."""
    from mfg_lightning.data.base import collate_samples

    return [
        collate_samples(samples[i : i + batch_size])
        for i in range(0, len(samples) - batch_size + 1, batch_size)
    ]


def steady_rate(stamps: list[float], warmup: int, batch_size: int) -> float:
    """Samples per second from the end-of-step timestamps, after ``warmup`` steps."""
    steps = len(stamps) - warmup
    return steps * batch_size / (stamps[-1] - stamps[warmup - 1])


def lightning_rate(
    overrides: list[str],
    batches: list[dict] | None,
    warmup: int,
    steps: int,
    precision: str = "32-true",
    loader=None,
    batch_size: int | None = None,
) -> float:
    """Training samples per second through ``lightning.Trainer.fit`` at ``precision``, on the
    in-memory ``batches`` or on ``loader`` (a real DataLoader, its loading included)."""
    import lightning as L

    stamps: list[float] = []

    class Stamp(L.Callback):
        def on_train_batch_end(self, *args, **kwargs) -> None:
            stamps.append(time.perf_counter())

    model, _ = build_model(overrides)
    trainer = L.Trainer(
        accelerator="cpu",
        devices=1,
        max_steps=warmup + steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        callbacks=[Stamp()],
        precision=precision,
    )
    data = loader if loader is not None else InMemory(batches, warmup + steps)
    trainer.fit(model, train_dataloaders=data)
    return steady_rate(stamps, warmup, batch_size or batches[0]["flow"].shape[0])


def patch_first_conv(net, how: str) -> None:
    """A candidate for the first convolution (2 input channels) under bf16 autocast, patched
    onto this network instance only: ``"fp32"`` runs it in float32 outside autocast (its output
    cast to bfloat16 once for the next layer); ``"pad8"`` zero-pads its input channels and
    weights to 8 (the same numbers: the padded channels are zeros)."""
    import torch.nn.functional as F

    conv = net.encoder[0]

    if how == "fp32":

        def forward(x):
            with torch.autocast("cpu", enabled=False):
                y = conv._conv_forward(x.float(), conv.weight, conv.bias)
            return y.to(torch.bfloat16) if torch.is_autocast_enabled("cpu") else y

    elif how == "pad8":

        def forward(x):
            pad = (0, 0, 0, 0, 0, 8 - x.shape[1])
            return conv._conv_forward(F.pad(x, pad), F.pad(conv.weight, pad), conv.bias)

    else:
        raise ValueError(how)
    conv.forward = forward


def bare_step_fn(
    model,
    channels_last: bool = False,
    compile_net: bool = False,
    autocast: bool = False,
    first_conv: str | None = None,
    conv_impls: dict[str, str] | None = None,
) -> Callable[[dict], None]:
    """One training step written in plain PyTorch, on the module's network, loss and optimiser.

    ``autocast``: the encoder under CPU bf16 autocast, the decoders in float32 (``MFG.decode``
    leaves autocast itself): what the module runs under ``trainer.precision=bf16-mixed``. The
    other options are the candidate speed-ups of the step; all off is the float32 reference.
    ``conv_impls``: an implementation per convolution (its module name → ``native``, ``im2col``
    or ``channels_last``), e.g. what ``model.net.conv_impl=auto`` chose.
    """
    from mfg_lightning.core import geometry
    from mfg_lightning.models.conv import switchable_layers

    net, loss_fn = model.net, model.loss_fn
    layers = dict(switchable_layers(net))
    for name, impl in (conv_impls or {}).items():
        layers[name].impl = impl
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    if first_conv:
        patch_first_conv(net, first_conv)
    optimizer = model.optimizer_factory(params=net.parameters())
    forward = torch.compile(net) if compile_net else net
    net.train()

    def step(batch: dict) -> None:
        flow, K = batch["flow"], batch["intrinsics"]
        height, width = flow.shape[-2:]
        if channels_last:
            flow = flow.contiguous(memory_format=torch.channels_last)
        t, w = geometry.pose_to_motion(batch["pose"])
        v_t = geometry.translational_field(t, K, height, width)
        v_w = geometry.rotational_field(w, K, height, width)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            out = forward(flow)
        terms = loss_fn(out.v_t.float(), out.v_omega.float(), v_t, v_w, out.hidden.float())
        optimizer.zero_grad()
        terms.total.backward()
        optimizer.step()

    return step


def bare_rate(
    overrides: list[str], batches: list[dict], warmup: int, steps: int, **options: Any
) -> float:
    """Training samples per second of :func:`bare_step_fn` (same model build and seed)."""
    model, _ = build_model(overrides)
    step = bare_step_fn(model, **options)
    stamps = []
    for batch in InMemory(batches, warmup + steps):
        step(batch)
        stamps.append(time.perf_counter())
    return steady_rate(stamps, warmup, batches[0]["flow"].shape[0])


def interleaved(fns: dict[str, Callable[[], float]], repeats: int) -> dict[str, list[float]]:
    """Call every function ``repeats`` times, interleaved (a, b, a, b, …): every value."""
    values: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            values[k].append(fn())
    return values


def median_of(fns: dict[str, Callable[[], float]], repeats: int) -> dict[str, float]:
    """Call every function ``repeats`` times, interleaved, and keep the median of each."""
    return {k: statistics.median(v) for k, v in interleaved(fns, repeats).items()}


def profile_step(
    overrides: list[str], batches: list[dict], steps: int, rows: int = 8, **options
) -> list[tuple]:
    """The bare step's most expensive operators: (name, ms per step, share of the step)."""
    from torch.profiler import ProfilerActivity, profile

    model, _ = build_model(overrides)
    step = bare_step_fn(model, **options)
    for batch in InMemory(batches, 3):
        step(batch)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for batch in InMemory(batches, steps):
            step(batch)
    events = [e for e in prof.key_averages() if e.self_cpu_time_total > 0]
    total = sum(e.self_cpu_time_total for e in events)
    top = sorted(events, key=lambda e: -e.self_cpu_time_total)[:rows]
    return [
        (e.key, e.self_cpu_time_total / 1e3 / steps, e.self_cpu_time_total / total) for e in top
    ]


def inference_rates(overrides: list[str], batches: list[dict], steps: int, repeats: int):
    """Frames per second of the bare network forward and of flow → (t, ω).

    The two alternate in short chunks (many more than ``repeats``), and each keeps the median
    chunk: a load spike on a shared machine hits both alike instead of one of them.
    """
    from mfg_lightning.core import geometry

    model, _ = build_model(overrides)
    model.eval()
    batch = batches[0]
    flow, K = batch["flow"], batch["intrinsics"]
    calls = {
        "forward": lambda: model.net(flow),
        "pose": lambda: model.predict_motion(flow, K),
    }
    chunk = max(2, steps // 5)
    rates: dict[str, list[float]] = {k: [] for k in calls}
    with torch.inference_mode():
        for fn in calls.values():
            fn()
        geometry.recover_motion(*model.net(flow)[:2], K)
        for _ in range(max(5, 5 * repeats)):
            for name, fn in calls.items():
                start = time.perf_counter()
                for _ in range(chunk):
                    fn()
                rates[name].append(chunk * flow.shape[0] / (time.perf_counter() - start))
    return {k: statistics.median(v) for k, v in rates.items()}


def generator_rate(overrides: list[str], n: int, repeats: int) -> float:
    """Samples per second of the synthetic dataset's ``__getitem__`` (one process)."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    dataset = instantiate(compose("train", overrides).dataset).dataset("train")

    def rate() -> float:
        start = time.perf_counter()
        for i in range(n):
            dataset[i]
        return n / (time.perf_counter() - start)

    return median_of({"generator": rate}, repeats)["generator"]


def generator_profile(overrides: list[str], n: int) -> list[tuple[str, float]]:
    """Where a synthetic sample's time goes: the package's functions (and the random draws),
    cumulative milliseconds per sample under ``cProfile``, most expensive first."""
    import cProfile
    import pstats

    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    dataset = instantiate(compose("train", overrides).dataset).dataset("train")
    dataset[0]
    profiler = cProfile.Profile()
    profiler.enable()
    for i in range(n):
        dataset[i]
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    rows = []
    for (path, _, func), (_, _, _, cumulative, _) in stats.items():
        if "mfg_lightning" in path:
            name = f"{Path(path).stem}.{func}"
        elif path == "~" and "numpy.random" in func:
            name = func.strip("<>").replace("method ", "")
        else:
            continue
        rows.append((name, 1e3 * cumulative / n))
    return sorted(rows, key=lambda r: -r[1])[:10]


def gemm_peak(dtype: torch.dtype, n: int, repeats: int) -> float:
    """GFLOP/s of an ``n × n`` matrix product in ``dtype`` (2 n³ FLOPs; median of ``repeats``
    timed products of ten, after two warm-up products)."""
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    for _ in range(2):
        a @ b
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(10):
            a @ b
        times.append((time.perf_counter() - start) / 10)
    return 2 * n**3 / statistics.median(times) / 1e9


def step_flops(overrides: list[str], batch: dict) -> tuple[float, float, float]:
    """FLOPs per sample of the network's forward, of its backward, and of the decoders' share
    of both, 2 FLOPs per multiply-add (``torch.utils.flop_counter.FlopCounterMode``:
    convolutions and matrix products, the weight and the input gradients; element-wise work,
    the loss and Adam count nothing)."""
    from torch.utils.flop_counter import FlopCounterMode

    from mfg_lightning.core import geometry

    model, _ = build_model(overrides)
    net, loss_fn = model.net, model.loss_fn
    flow, K = batch["flow"], batch["intrinsics"]
    t, w = geometry.pose_to_motion(batch["pose"])
    v_t = geometry.translational_field(t, K, *flow.shape[-2:])
    v_w = geometry.rotational_field(w, K, *flow.shape[-2:])
    with FlopCounterMode(display=False) as fwd:
        out = net(flow)
    terms = loss_fn(out.v_t, out.v_omega, v_t, v_w, out.hidden)
    with FlopCounterMode(display=False) as bwd:
        terms.total.backward()
    n = flow.shape[0]
    # The decoders analytically: forward, input and weight gradients of two M → 2hw products.
    decoders = 2 * 3 * 2 * net.hidden_units * net.decoder_t.out_features
    return fwd.get_total_flops() / n, bwd.get_total_flops() / n, decoders


def layer_kernels(overrides: list[str], batch: dict, bf16: bool, repeats: int) -> list[tuple]:
    """Every convolution and decoder of the network on its own, on the inputs it gets in the
    step: (layer, forward ms, backward ms, GFLOP/s of forward + backward). Under ``bf16`` the
    convolutions run under bf16 autocast and the decoders in float32, as in the module."""
    from torch import nn
    from torch.utils.flop_counter import FlopCounterMode

    model, _ = build_model(overrides)
    net = model.net.train()
    layers = [(n, m) for n, m in net.named_modules() if isinstance(m, nn.Conv2d | nn.Linear)]
    inputs: dict[str, torch.Tensor] = {}

    def keep(mod, inp, out, name: str) -> None:
        inputs.setdefault(name, inp[0].detach().clone())

    hooks = [m.register_forward_hook(partial(keep, name=name)) for name, m in layers]
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        net(batch["flow"])
    for h in hooks:
        h.remove()
    rows = []
    for i, (name, m) in enumerate(layers):
        # The flow needs no gradient; every later input does (the step back-propagates it).
        x = inputs[name].clone().requires_grad_(i > 0)
        autocast = bf16 and isinstance(m, nn.Conv2d)

        def forward(m=m, x=x, autocast=autocast):
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
                return m(x)

        with FlopCounterMode(display=False) as fc:
            y = forward()
            y.backward(torch.ones_like(y))
        flops = fc.get_total_flops()
        t_fwd, t_bwd = [], []
        for _ in range(repeats):
            start = time.perf_counter()
            y = forward()
            mid = time.perf_counter()
            y.backward(torch.ones_like(y))
            t_fwd.append(mid - start)
            t_bwd.append(time.perf_counter() - mid)
        f, b = statistics.median(t_fwd), statistics.median(t_bwd)
        # Conv2d for every convolution, SwitchableConv2d included (its native path here)
        kind = "Conv2d" if isinstance(m, nn.Conv2d) else type(m).__name__
        label = f"{name} {kind} {tuple(m.weight.shape)} in {tuple(x.shape[1:])}"
        rows.append((label, 1e3 * f, 1e3 * b, flops / (f + b) / 1e9))
    return rows


def datamodule(overrides: list[str]):
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    return instantiate(compose("train", overrides).dataset)


def loader_rate(loader, batches: int) -> float:
    """Samples per second of iterating ``loader`` (after its first batch: worker start-up)."""
    it = iter(loader)
    next(it)
    start, n = time.perf_counter(), 0
    for _ in range(batches):
        n += next(it)["flow"].shape[0]
    return n / (time.perf_counter() - start)


def bf16_bound(
    step_ms: dict[str, float],
    kernels: dict[str, list[tuple]],
    conv_flops: float,
    batch_size: int,
    bf16_peak: float,
) -> str:
    """What caps bf16-mixed's speed-up: the step split into its convolutions, its decoders and
    the rest (the step's time minus the layers', from the per-layer table), and the speed-up
    the step would have with every convolution at the bf16 GEMM peak and the rest as measured.
    """
    parts = {}
    for name, rows in kernels.items():
        conv = sum(f + b for label, f, b, _ in rows if "Conv2d" in label)
        dec = sum(f + b for label, f, b, _ in rows if "Linear" in label)
        parts[name] = (conv, dec, step_ms[name] - conv - dec)
    conv32, dec32, rest32 = parts["float32"]
    conv16, dec16, rest16 = parts["bf16-mixed"]
    at_peak = 1e3 * conv_flops * batch_size / 1e9 / bf16_peak
    bound = step_ms["float32"] / (at_peak + dec16 + rest16)
    worst = max(kernels["bf16-mixed"], key=lambda r: r[1] + r[2])
    share = (worst[1] + worst[2]) / step_ms["bf16-mixed"]
    rows = [
        ["convolutions", fmt(conv32, 1), fmt(conv16, 1), fmt(at_peak, 1)],
        ["the two decoders (float32 in both)", fmt(dec32, 1), fmt(dec16, 1), fmt(dec16, 1)],
        [
            "the rest (loss, geometry, Adam, casts, Lightning)",
            fmt(rest32, 1),
            fmt(rest16, 1),
            fmt(rest16, 1),
        ],
        [
            "the step (Lightning)",
            fmt(step_ms["float32"], 1),
            fmt(step_ms["bf16-mixed"], 1),
            fmt(at_peak + dec16 + rest16, 1),
        ],
    ]
    return (
        f"## What caps bf16-mixed, batch {batch_size}\n\n"
        + markdown_table(
            ["ms / step", "float32", "bf16-mixed", "bf16, convolutions at the bf16 GEMM peak"],
            rows,
        )
        + f"\nWith every convolution at the bfloat16 GEMM peak ({fmt(bf16_peak, 0)} GFLOP/s) and "
        f"the rest as measured, bf16-mixed would be at most **{bound:.2f}×** float32 at batch "
        f"{batch_size}; measured, its convolutions run at "
        f"{100 * at_peak / conv16:.0f} % of that peak on average. The most expensive kernel is "
        f"`{worst[0]}` ({100 * share:.0f} % of the bf16 step, at "
        f"{100 * worst[3] / bf16_peak:.0f} % of the bf16 peak). The decoders stay float32 by "
        "design (the fields must come out in float32: recovery from bf16-rounded fields errs "
        "up to 5e-4 m)."
    )


#: Runs the command given as its arguments and prints the child's peak RSS in kilobytes. The
#: measurement runs in this small process because Linux counts, in a child's peak RSS, the
#: memory of the process that forked it up to the exec: forked from the benchmark itself (a
#: couple of GB by then) the number would be the benchmark's, not the training run's.
_RSS_PROBE = """
import os, subprocess, sys
proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
_, status, usage = os.wait4(proc.pid, 0)
sys.stderr.write(proc.stderr.read().decode()[-2000:] if status else "")
print(usage.ru_maxrss)
sys.exit(1 if status else 0)
"""


def peak_rss_mb(steps: int, tiny: bool, threads: int) -> tuple[float, float]:
    """Peak resident memory (MB) and wall time of ``python -m mfg_lightning.train`` for a few
    steps of the quick-start config (no logger, no validation, no test)."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "mfg_lightning.train",
            f"trainer.max_steps={steps}",
            "trainer.limit_val_batches=0",
            "logger=none",
            "callbacks=none",
            "test=false",
            f"hydra.run.dir={tmp}",
            f"paths.cache_dir={tmp}/cache",
            *(["debug=tiny"] if tiny else []),
        ]
        start = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-c", _RSS_PROBE, *cmd],
            cwd=tmp,
            env={**os.environ, "OMP_NUM_THREADS": str(threads)},
            capture_output=True,
            text=True,
            check=False,
        )
        seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr}")
    # ru_maxrss is in kilobytes on Linux (bytes on macOS).
    scale = 1 / 1024 if sys.platform != "darwin" else 1 / 2**20
    return int(proc.stdout.split()[-1]) * scale, seconds


PRECISIONS = {"float32": "32-true", "bf16-mixed": "bf16-mixed"}
TITLE = "Throughput: training, inference, data, memory"
#: The marker of section 7's block in throughput.md (:meth:`Report.write_section`).
CONV_MARKER = "conv-impl"


def with_conv_impl(overrides: list[str], impl: str) -> list[str]:
    """``overrides`` with ``model.net.conv_impl=<impl>`` in place of any earlier value."""
    return [o for o in overrides if not o.startswith("model.net.conv_impl=")] + [
        f"model.net.conv_impl={impl}"
    ]


def conv_layer_rows(
    overrides: list[str], shape: tuple[int, ...], dtype: torch.dtype, repeats: int
) -> tuple[list[list[str]], dict[str, str]]:
    """Every convolution timed alone under each implementation, as ``model.net.conv_impl=auto``
    times it at the start of training (nothing cached): the table rows (a total row last) and
    the choice, layer name → implementation."""
    from mfg_lightning.models.conv import CONV_IMPLS, choose_conv_impls, switchable_layers

    model, _ = build_model(with_conv_impl(overrides, "auto"))
    net = model.net.train()
    layers = dict(switchable_layers(net))
    # min_cpu_share=0: the table shows what the times pick; the environment gives the load
    choices = choose_conv_impls(net, shape, dtype, None, repeats, min_cpu_share=0.0)
    rows, totals = [], dict.fromkeys([*CONV_IMPLS, "chosen"], 0.0)
    for c in choices:
        conv = layers[c.name]
        (k, _), (s, _), (p, _) = conv.kernel_size, conv.stride, conv.padding
        h, w = c.shape[-2:]
        out = f"{(h + 2 * p - k) // s + 1}×{(w + 2 * p - k) // s + 1}"
        times = [fmt(c.ms[i], 2) if i in c.ms else "-" for i in CONV_IMPLS]
        for impl in CONV_IMPLS:
            totals[impl] += c.ms.get(impl, float("nan"))
        totals["chosen"] += c.ms[c.choice]
        rows.append(
            [f"`{c.name}` {conv.in_channels}→{conv.out_channels}, {k}×{k} / {s}",
             f"{h}×{w} → {out}", str(dtype).removeprefix("torch."), *times, c.choice,
             fmt(c.ms["native"] / c.ms[c.choice], 2)]
        )  # fmt: skip
    rows.append(
        ["all convolutions", "", str(dtype).removeprefix("torch."),
         *(fmt(totals[i], 2) for i in CONV_IMPLS), "per layer",
         fmt(totals["native"] / totals["chosen"], 2)]
    )  # fmt: skip
    return rows, {c.name: c.choice for c in choices}


def conv_section(
    args: argparse.Namespace, base: list[str], cfg: Any, samples: list[dict] | None = None
) -> Path:
    """7. The convolutions' implementations: each layer timed alone (native, im2col,
    channels-last) at the training batch in every dtype training may compute in on this CPU,
    what ``model.net.conv_impl=auto`` picks, and the bare training step with that choice
    against all native. Written as its own section of throughput.md (the rest kept)."""
    from _common import cpu_description

    from mfg_lightning.run.convolutions import measured_dtype

    batch_size = 4 if args.tiny else int(cfg.dataset.batch_size)
    if samples is None:
        samples = render(cfg, 2 * batch_size)
    batches = make_batches(samples, batch_size)
    height, width = int(cfg.dataset.height), int(cfg.dataset.width)
    dtypes = [torch.float32]
    if measured_dtype("bf16-mixed") == torch.bfloat16:
        dtypes.append(torch.bfloat16)
    report = Report("throughput", TITLE, args.out)
    report.add(
        f"CPU: {cpu_description()}; torch threads: {torch.get_num_threads()}. MFG "
        f"{height} × {width}, M = {cfg.model.net.hidden_units}, batch {batch_size} (the "
        "training batch)"
        + ("" if len(dtypes) > 1 else "; bfloat16 not measured: this CPU lacks native bfloat16 "
           "(AVX512-BF16, AMX), so bf16-mixed training chooses for float32 only")
        + "."
    )  # fmt: skip
    rows, steps = [], []
    native = with_conv_impl(base, "native")
    for dtype in dtypes:
        layer_rows, choice = conv_layer_rows(
            base, (batch_size, 2, height, width), dtype, args.conv_repeats
        )
        rows += layer_rows
        bf16 = dtype == torch.bfloat16
        runs = interleaved(
            {
                "native": partial(bare_rate, native, batches, args.warmup, args.conv_steps,
                                  autocast=bf16),
                "auto": partial(bare_rate, native, batches, args.warmup, args.conv_steps,
                                autocast=bf16, conv_impls=choice),
            },
            args.repeats,
        )  # fmt: skip
        pairs = [a / n for a, n in zip(runs["auto"], runs["native"], strict=True)]
        steps.append(
            [batch_size, str(dtype).removeprefix("torch."),
             fmt(statistics.median(runs["native"]), 1), fmt(statistics.median(runs["auto"]), 1),
             ratio_cell(pairs)]
        )  # fmt: skip
    report.add(
        markdown_table(
            [
                "layer (C_in→C_out, kernel / stride)",
                "map (in → out)",
                "dtype",
                "native (ms)",
                "im2col (ms)",
                "channels-last (ms)",
                "chosen",
                "native / chosen",
            ],
            rows,
        )
        + f"\nEach convolution alone, forward + backward (the weight gradient, and the input "
        "gradient except for the first layer's, the flow), on a random input of the shape and "
        "dtype it gets in the training step, timed as `model.net.conv_impl=auto` times it at "
        f"the start of training: the best of {args.conv_repeats} after one warm-up, the three "
        "interleaved; bfloat16: the forward under CPU autocast. The input is NCHW; an "
        "implementation's own copies (channels-last: the input to NHWC; im2col: the padded "
        "input and the gathered rows) are timed with it. *Chosen*: the fastest, native unless "
        "another is at least 5 % faster; `native / chosen`: the layer's speed-up."
    )
    report.add(
        "Training step with the chosen implementations against native:\n\n"
        + markdown_table(
            [
                "batch",
                "dtype",
                "native (samples/s)",
                "auto's choice (samples/s)",
                "auto / native (range)",
            ],
            steps,
        )
        + f"\nThe bare training loop (section 1: the network, loss and fused Adam; bfloat16: "
        f"the encoder under autocast), {args.warmup} warm-up then {args.conv_steps} steps per "
        f"rate, {args.repeats} interleaved repeats, medians; the ratio of each back-to-back "
        "pair, then their median (range)."
    )
    return report.write_section(CONV_MARKER, "Convolution implementations per layer")


#: Overrides that turn the sample cache and its prefetch off: what the other sections' data
#: rows measure (the generator itself).
UNCACHED_SAMPLES = [
    "dataset.sample_cache.memory_mb=0",
    "dataset.sample_cache.disk=false",
    "dataset.prefetch=none",
]
#: The marker of the sample cache's block in throughput.md (:meth:`Report.write_section`).
SAMPLE_CACHE_MARKER = "sample-cache"
#: The loaders the sample cache section compares: label → (dataset overrides, whether an
#: earlier run filled the disk tier first).
CACHE_LOADERS: dict[str, tuple[list[str], bool]] = {
    "no cache: every sample generated when the loader asks": (UNCACHED_SAMPLES, False),
    "cache, `prefetch=none`": (["dataset.prefetch=none"], False),
    "cache, `prefetch=thread` (the default)": (["dataset.prefetch=thread"], False),
    "cache, `prefetch=worker`": (["dataset.prefetch=worker"], False),
    "cache on disk only, filled by an earlier run (`memory_mb=0`)": (
        ["dataset.sample_cache.memory_mb=0", "dataset.prefetch=none"],
        True,
    ),
}


def with_overrides(overrides: list[str], extra: list[str]) -> list[str]:
    """``overrides`` then ``extra``, an earlier value of a key that ``extra`` sets left out."""
    keys = {o.split("=", 1)[0] for o in extra}
    return [o for o in overrides if o.split("=", 1)[0] not in keys] + extra


def cache_datamodule(base: list[str], extra: list[str], cache_dir: Path, frames: int, batch: int):
    """The synthetic DataModule of ``base`` + ``extra`` on 2 training trajectories of
    ``frames`` frames, batch ``batch``, its sample cache's disk tier in ``cache_dir``."""
    size = [
        "dataset.train_sequences=2",
        f"dataset.sequence_length={frames}",
        f"dataset.batch_size={batch}",
        f"dataset.cache_dir={cache_dir}",
    ]
    return datamodule(with_overrides(base, [*size, *extra]))


def served(dm, before: dict[str, int] | None = None) -> dict[str, int]:
    """How this process's training dataset has served its samples (memory, disk, computed:
    :attr:`~mfg_lightning.data.sample_cache.SampleStore.counts`), less ``before``; empty without
    a cache. A loader worker's own counts are not seen here."""
    store = getattr(dm.dataset("train"), "store", None)
    counts = {} if store is None else dict(store.counts)
    counts.pop("prefetched", None)
    return {k: v - (before or {}).get(k, 0) for k, v in counts.items()}


def served_text(counts: dict[str, int], workers: bool) -> str:
    """A table cell for :func:`served`'s counts."""
    if workers:
        return "(in the worker)"
    if not counts:
        return "computed (no cache)"
    return ", ".join(f"{k} {v}" for k, v in counts.items() if v) or "nothing"


def loader_epochs(dm) -> tuple[float, float, dict[str, int]]:
    """Samples per second of iterating ``dm``'s training loader through its first epoch (after
    its first batch: a worker's start-up) and its second, and how epoch 2's samples were served
    (:func:`served`)."""
    loader = dm.train_dataloader()
    rates, counts = [], served(dm)
    for epoch in (0, 1):
        loader.order.set_epoch(epoch)  # what Lightning does at the start of each epoch
        batches = iter(loader)
        if epoch == 0:
            next(batches)
        else:
            counts = served(dm)
        start, n = time.perf_counter(), 0
        for batch in batches:
            n += batch["flow"].shape[0]
        rates.append(n / (time.perf_counter() - start))
    epoch2 = served(dm, counts)
    dm.teardown("fit")
    return rates[0], rates[1], epoch2


def training_epochs(
    overrides: list[str], data, warmup: int, epochs: int = 2
) -> tuple[float, float]:
    """Training samples per second (Lightning, float32) on ``data`` (a DataModule: its training
    loader; else an iterable of batches) in the first epoch (after ``warmup`` steps) and in the
    ``epochs - 1`` after it together (their first step included)."""
    import lightning as L

    stamps: list[tuple[int, float, int]] = []

    class Stamp(L.Callback):
        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
            stamps.append((trainer.current_epoch, time.perf_counter(), batch["flow"].shape[0]))

    model, _ = build_model(overrides)
    trainer = L.Trainer(
        accelerator="cpu", devices=1, max_epochs=epochs, max_steps=-1, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        num_sanity_val_steps=0, limit_val_batches=0, callbacks=[Stamp()],
    )  # fmt: skip
    if isinstance(data, L.LightningDataModule):
        trainer.fit(model, datamodule=data)
    else:
        trainer.fit(model, train_dataloaders=data)
    first = [s for s in stamps if s[0] == 0]
    later = [s for s in stamps if s[0] >= 1]
    rate1 = sum(n for _, _, n in first[warmup:]) / (first[-1][1] - first[warmup - 1][1])
    rate2 = sum(n for _, _, n in later) / (later[-1][1] - first[-1][1])
    return rate1, rate2


def quick_start_wall(tiny: bool, threads: int) -> list[list[str]]:
    """Wall time of ``python -m mfg_lightning.train`` (the quick start; ``debug=tiny`` when
    ``tiny``) without the sample cache, with it from empty, and with its disk tier filled by
    the run before (a multirun's next job), each with its training time, the precision
    ``auto`` chose and its test metrics: table rows."""
    import json

    from omegaconf import OmegaConf

    runs = {
        "without the cache (`memory_mb=0 disk=false prefetch=none`)": (UNCACHED_SAMPLES, "a"),
        "the defaults, empty cache": ([], "b"),
        "the defaults, disk tier filled by the run before": ([], "b"),
    }
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, (extra, cache)) in enumerate(runs.items()):
            run_dir = Path(tmp) / f"run{i}"
            cmd = [
                sys.executable, "-m", "mfg_lightning.train", f"hydra.run.dir={run_dir}",
                f"paths.cache_dir={tmp}/cache-{cache}", *(["debug=tiny"] if tiny else []), *extra,
            ]  # fmt: skip
            start = time.perf_counter()
            proc = subprocess.run(
                cmd, cwd=tmp, env={**os.environ, "OMP_NUM_THREADS": str(threads)},
                capture_output=True, text=True, check=False,
            )  # fmt: skip
            wall = time.perf_counter() - start
            if proc.returncode != 0:
                raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr[-3000:]}")
            result = json.loads((run_dir / "metrics.json").read_text())
            precision = OmegaConf.load(run_dir / "config.yaml").trainer.precision
            results.append((label, wall, result, precision))
    before = results[0][1]
    return [
        [label, fmt(wall, 1), fmt(before / wall, 2), fmt(result["train_seconds"], 1), precision,
         fmt(result["metrics"]["test/ate"], 5), fmt(result["metrics"]["test/rpe_rot"], 6)]
        for label, wall, result, precision in results
    ]  # fmt: skip


def quick_start_section(args: argparse.Namespace) -> Path:
    """The quick start's wall time without and with the sample cache (:func:`quick_start_wall`)
    as a section of its own, one per instruction set torch's kernels run (an instruction-set cap
    set, :func:`~mfg_lightning.core.machine.isa_caps`: an imitated machine, said in the
    heading)."""
    caps = isa_caps()
    capability = torch.backends.cpu.get_cpu_capability()
    report = Report("throughput", TITLE, args.out)
    imitated = ", ".join(f"`{k}={v}`" for k, v in caps.items())
    report.add(
        "`python -m mfg_lightning.train`" + (" debug=tiny" if args.tiny else "")
        + f" (training, validation, test) with torch's kernels at {capability}"
        + (f", capped by {imitated}: an imitation of that machine on this one (its instruction "
           "set, not its cores or caches)" if caps else "")
        + ":\n\n"
        + markdown_table(
            ["run", "wall time (s)", "speed-up", "training (s)", "precision (`auto`)",
             "test ATE (m)", "test RPE rot (rad)"],
            quick_start_wall(args.tiny, torch.get_num_threads()),
        )
        + "\nOne run each, one after the other. The cache hands out the generated samples bit "
        "for bit (tests/test_sample_cache.py): the test metrics differ only by the training's "
        "own run-to-run variation."
    )  # fmt: skip
    marker = f"quick-start-{capability.lower()}" + ("-capped" if caps else "")
    heading = f"The quick start at {capability}" + (" (imitated)" if caps else "")
    return report.write_section(marker, heading)


def sample_cache_section(args: argparse.Namespace, cfg: Any) -> Path:
    """The sample cache: the training loader alone and training on it (Lightning, float32) in
    the first epoch (samples computed: no cache, the cache with each prefetch, the disk tier of
    an earlier run) and the later ones (read back: ``--cache-epochs``), against training on the
    same batches held in memory. Written as its own section of throughput.md (the rest kept);
    the quick start without and with the cache is :func:`quick_start_section`'s."""
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    # The dataset's own cache settings underneath each row: base_overrides turns the cache off
    # (for the other sections), and a row's overrides only change the keys they name.
    base = [o for o in base_overrides(args.tiny) if o not in UNCACHED_SAMPLES]
    frames = 12 if args.tiny else args.cache_frames
    batch = 4 if args.tiny else int(cfg.dataset.batch_size)
    warmup = 1 if args.tiny else 3
    repeats = 1 if args.tiny else args.candidate_repeats
    epochs = 2 if args.tiny else max(2, args.cache_epochs)
    later = "epoch 2" if epochs == 2 else f"epochs 2–{epochs}"
    report = Report("throughput", "Throughput: training, inference, data, memory", args.out)
    # What the loaders are measured against: training on the training loader's own batches
    # (every field, the short last one too), collated once and held in memory, for as many
    # epochs, timed the same way, right after each loader's training (a pair: a change of the
    # machine's speed between pairs cancels out of their ratio).
    with tempfile.TemporaryDirectory() as cache:  # (no cache: nothing is written there)
        loader = cache_datamodule(base, UNCACHED_SAMPLES, Path(cache), frames, batch)
        loader = loader.train_dataloader()
        batches = list(loader)
    rates: dict[str, list[tuple[float, ...]]] = {label: [] for label in CACHE_LOADERS}
    held: list[tuple[float, float]] = []
    sources: dict[str, str] = {}
    n_train = 0
    for _ in range(repeats):
        for label, (extra, prefilled) in CACHE_LOADERS.items():
            row = []
            for measure in ("loader", "training"):
                with tempfile.TemporaryDirectory() as cache:
                    if prefilled:  # an earlier run's first epoch
                        loader_epochs(cache_datamodule(base, [], Path(cache), frames, batch))
                    dm = cache_datamodule(base, extra, Path(cache), frames, batch)
                    n_train = len(dm.dataset("train"))
                    if measure == "loader":
                        *loader_rates, counts = loader_epochs(dm)
                        row += loader_rates
                        sources[label] = served_text(
                            counts, dm.num_workers > 0 or "dataset.prefetch=worker" in extra
                        )
                    else:
                        row += training_epochs(base, dm, warmup, epochs)
            memory = InMemory(batches, len(batches))
            held.append(training_epochs(base, memory, warmup, epochs))
            rates[label].append((*row, *held[-1]))
    mem1, mem2 = (statistics.median(r[k] for r in held) for k in range(2))
    rows = []
    for label, runs in rates.items():
        loader1, loader2, train1, train2 = (statistics.median(r[k] for r in runs) for k in range(4))
        pairs1 = [r[2] / r[4] for r in runs]
        pairs2 = [r[3] / r[5] for r in runs]
        rows.append(
            [label, fmt(loader1, 0), fmt(loader2, 0), sources[label], fmt(train1, 1),
             f"{100 * (1 - statistics.median(pairs1)):.0f} %", fmt(train2, 1),
             f"{100 * (1 - statistics.median(pairs2)):.0f} %", ratio_cell(pairs2)]
        )  # fmt: skip
    rows.append(
        ["the same batches, collated once, in memory", "-", "-", "-", fmt(mem1, 1), "0 %",
         fmt(mem2, 1), "0 %", "1"]
    )  # fmt: skip
    report.add(
        f"MFG {cfg.dataset.height} × {cfg.dataset.width}, M = {cfg.model.net.hidden_units}, "
        f"float32, batch {batch}; 2 training trajectories of {frames} frames ({n_train} training "
        f"samples per epoch); {torch.get_num_threads()} torch threads; medians of {repeats} "
        "repeats, each on an empty cache.\n\n"
        + markdown_table(
            [
                "loader",
                "loader alone, epoch 1 (samples/s)",
                "loader alone, epoch 2",
                "epoch 2's samples served from",
                "training, epoch 1 (samples/s)",
                "epoch 1 waiting on data",
                f"training, {later}",
                f"{later} waiting on data",
                f"{later} / in memory",
            ],
            rows,
        )
        + "\n*Loader alone*: iterating the training loader (shuffled, collated) through epoch 1 "
        "after its first batch (a worker's start-up excluded) and through epoch 2; *served from*: "
        "the training dataset's own count of where epoch 2's samples came from in the loader-"
        "alone run (memory, its disk files, computed). *Training*: "
        f"`lightning.Trainer.fit` for {epochs} epochs on the DataModule, epoch 1 after "
        f"{warmup} steps, {later} whole; *waiting on data* = 1 − rate / the rate of the same "
        "epochs on the training loader's own batches (every field, the short last batch too) "
        "collated once and held in memory, timed the same way right after it (the median of the "
        f"repeats' pairs; *{later} / in memory*: their median (range), *noisy* where the range "
        f"leaves ±{100 * NOISY:.0f} % of it). Epoch 1 computes every sample (the disk row "
        "reads an earlier run's entries); from epoch 2 on the cached loaders read memory (the "
        "disk row: its files). `prefetch=thread` computes ahead in a thread of the training "
        "process, in the loader's order; `prefetch=worker` in one persistent loader process. "
        "Both compete with the training step's threads for the cores."
    )
    return report.write_section(SAMPLE_CACHE_MARKER, "The sample cache: samples computed once")


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    if args.tiny:
        args.samples, args.steps_per_batch_size = 8, [4, 2, 2]
        args.batch_sizes, args.warmup, args.rss_steps = [1, 2, 4], 2, 2
        args.repeats = args.candidate_repeats = 1
        args.no_compile = True
        args.conv_repeats, args.conv_steps = 1, 2
    if len(args.steps_per_batch_size) != len(args.batch_sizes):
        raise SystemExit("error: give one --steps-per-batch-size per --batch-sizes")
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    if args.quick_start:  # (subprocesses: no model built here)
        return quick_start_section(args)
    base = base_overrides(args.tiny)
    _, cfg = build_model(base)
    if args.sample_cache:
        return sample_cache_section(args, cfg)
    if args.convolutions:
        return conv_section(args, base, cfg)
    report = Report("throughput", TITLE, args.out)
    height, width = cfg.dataset.height, cfg.dataset.width
    samples = render(cfg, max(args.samples, *args.batch_sizes))
    sizes = list(zip(args.batch_sizes, args.steps_per_batch_size, strict=True))
    largest = max(args.batch_sizes)
    report.add(
        f"MFG {height} × {width}, M = {cfg.model.net.hidden_units}, channels "
        f"{list(cfg.model.net.channels)}, fused Adam (the default); {args.samples} synthetic "
        f"samples in memory, pre-collated; rates are medians of {args.repeats} (Lightning/bare) "
        f"or {args.candidate_repeats} (candidates) interleaved runs, each "
        f"{args.warmup} warm-up steps then {args.steps_per_batch_size} steps (per batch size "
        f"{args.batch_sizes})."
    )

    # 0. The machine's GEMM peaks and the model's FLOPs.
    n = 256 if args.tiny else 2048
    peaks = {
        "float32": gemm_peak(torch.float32, n, args.repeats),
        "bf16-mixed": gemm_peak(torch.bfloat16, n, args.repeats),
    }
    fwd_flops, bwd_flops, dec_flops = step_flops(base, make_batches(samples, largest)[0])
    flops = fwd_flops + bwd_flops
    report.add(
        "## GEMM peak and the model's FLOPs\n\n"
        + markdown_table(
            ["", "value"],
            [
                [f"{n}² matmul, float32 (GFLOP/s)", fmt(peaks["float32"], 0)],
                [f"{n}² matmul, bfloat16 (GFLOP/s)", fmt(peaks["bf16-mixed"], 0)],
                ["bfloat16 / float32", fmt(peaks["bf16-mixed"] / peaks["float32"], 2)],
                ["network forward (GFLOP / sample)", fmt(fwd_flops / 1e9, 3)],
                ["network backward (GFLOP / sample)", fmt(bwd_flops / 1e9, 3)],
                ["of which the two decoders (GFLOP / sample)", fmt(dec_flops / 1e9, 3)],
            ],
        )
        + "\nPeaks: median of timed products in this run (2 n³ FLOPs each). FLOPs: "
        "`torch.utils.flop_counter.FlopCounterMode` around the network's forward and around "
        f"the loss's backward at batch {largest}, divided by the batch: convolutions and matrix "
        "products (forward, input and weight gradients; the flow needs no gradient), nothing "
        "for element-wise work, the loss, the upsampling or Adam. A rate's fraction of the peak "
        "below is samples/s × these FLOPs / the peak of its own dtype (bf16-mixed: the bfloat16 "
        "peak, although its decoders run in float32). A 2048² float32 GEMM is not float32's "
        "ceiling on this CPU: oneDNN's float32 convolutions run faster (fractions above 100 %)."
    )

    def frac(rate: float, precision: str) -> str:
        return f"{100 * rate * flops / 1e9 / peaks[precision]:.1f} %"

    # 1. Lightning against the bare loop, float32 and bf16-mixed side by side.
    rows, train_rates = [], {}
    for batch_size, steps in sizes:
        batches = make_batches(samples, batch_size)
        fns = {}
        for name, precision in PRECISIONS.items():
            fns[(name, "lightning")] = partial(
                lightning_rate, base, batches, args.warmup, steps, precision
            )
            fns[(name, "bare")] = partial(
                bare_rate, base, batches, args.warmup, steps, autocast=precision != "32-true"
            )
        runs = interleaved(fns, args.repeats)
        for name in PRECISIONS:
            lit, bare = runs[(name, "lightning")], runs[(name, "bare")]
            r = {"lightning": statistics.median(lit), "bare": statistics.median(bare)}
            # The ratio of each back-to-back pair, then their median: a change of the machine's
            # load between pairs cancels out.
            pairs = [a / b for a, b in zip(lit, bare, strict=True)]
            train_rates[(batch_size, name)] = r
            train_rates[(batch_size, name, "runs")] = (lit, bare)
            rows.append(
                [
                    batch_size,
                    name,
                    fmt(r["lightning"], 1),
                    fmt(r["bare"], 1),
                    ratio_cell(pairs),
                    fmt(1e3 * batch_size / r["lightning"], 1),
                    fmt(1e3 * batch_size / r["lightning"] - 1e3 * batch_size / r["bare"], 2),
                    frac(r["lightning"], name),
                    frac(r["bare"], name),
                ]
            )
    report.add(
        "## Training: Lightning Trainer against a bare PyTorch loop (target ≥ 0.95×)\n\n"
        + markdown_table(
            [
                "batch",
                "precision",
                "Lightning (samples/s)",
                "bare loop (samples/s)",
                "ratio (range)",
                "Lightning ms/step",
                "Lightning − bare (ms/step)",
                "Lightning, of GEMM peak",
                "bare, of GEMM peak",
            ],
            rows,
        )
        + "\nLightning: `lightning.Trainer(precision=...)`, `32-true` or `bf16-mixed`, on the "
        "module's `training_step`; the bare loop: the same network, loss and fused Adam, the "
        "encoder under `torch.autocast('cpu', dtype=torch.bfloat16)` for bf16-mixed (the "
        "decoders leave autocast and run in float32, as in the module). The Trainer runs without "
        "logger, checkpointing or progress bar. What Lightning adds is a fixed cost per step, "
        "whatever the batch: its loop (about 40 hook calls), the optimiser closure and the "
        "result collection of `self.log`, which the module calls only on the logging steps; at "
        "batch 1 that fixed cost is what separates the ratio from 1. *Ratio*: that of each "
        f"back-to-back pair of {args.repeats} interleaved repeats, their median (range); "
        f"*noisy*: the range leaves ±{100 * NOISY:.0f} % of the median, here and in every "
        "ratio below."
    )
    ratio_rows = []
    for batch_size, _ in sizes:
        target = {32: "≥ 2.2", 16: "≥ 1.8"}.get(batch_size, "-")
        lit32, bare32 = train_rates[(batch_size, "float32", "runs")]
        lit16, bare16 = train_rates[(batch_size, "bf16-mixed", "runs")]
        pl = [a / b for a, b in zip(lit16, lit32, strict=True)]
        pb = [a / b for a, b in zip(bare16, bare32, strict=True)]
        ratio_rows.append(
            [
                batch_size,
                ratio_cell(pl, 2),
                ratio_cell(pb, 2),
                target,
            ]
        )
    report.add(
        "## bf16-mixed against float32\n\n"
        + markdown_table(
            ["batch", "Lightning bf16 / fp32 (range)", "bare bf16 / fp32 (range)", "target"],
            ratio_rows,
        )
        + "\nThe ratio of each interleaved repeat (float32 and bf16 run back to back), then "
        "their median."
    )

    # 2. Inference.
    inf_rows = []
    for batch_size, steps in sizes:
        batches = make_batches(samples, batch_size)
        r = inference_rates(base, batches, max(steps, 10), args.candidate_repeats)
        inf_rows.append(
            [
                batch_size,
                fmt(r["forward"], 1),
                fmt(r["pose"], 1),
                f"{100 * (r['forward'] / r['pose'] - 1):+.1f} %",
            ]
        )
    report.add(
        "## Inference: flow → (t, ω) against the bare forward (target ≤ +10 %)\n\n"
        + markdown_table(
            ["batch", "forward (frames/s)", "flow → (t, ω) (frames/s)", "time added"], inf_rows
        )
        + "\n`predict_motion` = `MFG.forward` + `geometry.recover_motion` (cached "
        "pseudo-inverses), `torch.inference_mode`, float32."
    )

    # 3. The data: loader-only rates, and training on the real loaders.
    data_batch = cfg.dataset.batch_size if not args.tiny else 4
    n_batches = 2 if args.tiny else 20
    gen = generator_rate(base, 20 if args.tiny else 300, args.candidate_repeats)
    load_rows = [["exact-flow generator, `__getitem__` in the training process", fmt(gen, 0)]]
    loaders = {}
    for workers in (0, 1):
        dm = datamodule(
            [*base, f"dataset.num_workers={workers}", f"dataset.batch_size={data_batch}"]
        )
        loaders[workers] = dm
        rate = statistics.median(
            loader_rate(dm.train_dataloader(), n_batches) for _ in range(args.candidate_repeats)
        )
        where = "the training process" if workers == 0 else "one DataLoader worker"
        load_rows.append([f"exact-flow generator, train loader, {where}", fmt(rate, 0)])
    with tempfile.TemporaryDirectory() as cache:
        frames = 21 if args.tiny else 60
        dis = datamodule(
            [
                *base,
                "flow=dis",
                f"dataset.cache_dir={cache}",
                f"dataset.sequence_length={frames}",
                "dataset.train_sequences=1",
                "dataset.test_sequences=1",
                f"dataset.batch_size={data_batch}",
            ]
        )
        start = time.perf_counter()
        dis.prepare_data()
        prepare_s = time.perf_counter() - start
        n_dis = len(dis.dataset("train"))
        dis_batches = max(1, n_dis // data_batch - 1)
        rate = statistics.median(
            loader_rate(dis.train_dataloader(), dis_batches) for _ in range(args.candidate_repeats)
        )
        load_rows.append(
            [
                f"cached rendered DIS flow (`flow=dis`, {n_dis} cached train pairs), train "
                "loader, the training process",
                fmt(rate, 0),
            ]
        )
    train_data_rows = []
    for name, precision in PRECISIONS.items():
        batches = make_batches(samples, data_batch)
        steps = 4 if args.tiny else 30
        mem = statistics.median(
            lightning_rate(base, batches, args.warmup, steps, precision)
            for _ in range(args.candidate_repeats)
        )
        real = {}
        for workers, dm in loaders.items():
            real[workers] = statistics.median(
                lightning_rate(
                    base,
                    None,
                    args.warmup,
                    steps,
                    precision,
                    loader=dm.train_dataloader(),
                    batch_size=data_batch,
                )
                for _ in range(args.candidate_repeats)
            )
        train_data_rows.append(
            [
                name,
                fmt(mem, 1),
                fmt(real[0], 1),
                f"{100 * (1 - real[0] / mem):.0f} %",
                fmt(real[1], 1),
                f"{100 * (1 - real[1] / mem):.0f} %",
            ]
        )
    report.add(
        f"## The data: loader-only rates and training on the real loader (batch {data_batch})\n\n"
        + markdown_table(["loader only", "samples/s"], load_rows)
        + f"\nLoader-only: iterating the configured train DataLoader (shuffled, collated, batch "
        f"{data_batch}) {n_batches} batches after its first one (a worker's start-up excluded); "
        f"the DIS cache was filled first by `prepare_data` ({prepare_s:.0f} s: render and "
        "estimate every pair), then read.\n\nTraining on the real loader:\n\n"
        + markdown_table(
            [
                "precision",
                "training, batches in memory (samples/s)",
                "training, generator in process (`num_workers=0`, the default)",
                "time waiting on data",
                "training, 1 loader worker",
                "time waiting on data",
            ],
            train_data_rows,
        )
        + '\nLightning, the same model and precision; "waiting on data" = 1 − rate on the real '
        "loader / rate on batches in memory. With `num_workers=0` the generator runs between the "
        "steps, so its time adds to every step; a worker overlaps it, but takes one of the "
        "machine's cores from the training's threads."
    )
    gen_profile = generator_profile(base, 10 if args.tiny else 200)
    report.add(
        "Where an exact-flow sample's time goes (cProfile, cumulative, so nested calls "
        "repeat):\n\n"
        + markdown_table(
            ["function", "ms / sample"], [[f"`{name}`", fmt(ms, 3)] for name, ms in gen_profile]
        )
    )

    # 4. Peak memory of a real training run.
    rss, seconds = peak_rss_mb(args.rss_steps, args.tiny, torch.get_num_threads())
    report.add(
        "## Peak resident memory of a training run\n\n"
        + markdown_table(
            ["run", "peak RSS (MB)", "wall time (s)"],
            [
                [
                    f"`python -m mfg_lightning.train trainer.max_steps={args.rss_steps} "
                    "trainer.limit_val_batches=0 logger=none callbacks=none test=false"
                    + (" debug=tiny" if args.tiny else "")
                    + f"` (batch {4 if args.tiny else 16}, the default loader: each sample "
                    "generated once, then read from the sample cache)",
                    fmt(rss, 0),
                    fmt(seconds, 1),
                ]
            ],
        )
    )

    # 5. Where the step's time goes, per operator and per layer.
    batches = make_batches(samples, largest)
    steps = dict(sizes)[largest]
    for name, precision in PRECISIONS.items():
        prof = profile_step(
            base, batches, max(3, steps // 3), rows=12, autocast=precision != "32-true"
        )
        report.add(
            f"## Profile of the bare training step, batch {largest}, {name}\n\n"
            + markdown_table(
                ["operator", "ms / step (self)", "share"],
                [[op, fmt(ms, 2), f"{100 * share:.0f} %"] for op, ms, share in prof],
            )
        )
    kernels = {
        name: layer_kernels(base, batches[0], precision != "32-true", max(3, args.repeats))
        for name, precision in PRECISIONS.items()
    }
    kernel_rows = []
    for (label, f32, b32, g32), (_, f16, b16, g16) in zip(
        kernels["float32"], kernels["bf16-mixed"], strict=True
    ):
        kernel_rows.append(
            [
                f"`{label}`",
                f"{fmt(f32, 2)} / {fmt(b32, 2)}",
                f"{fmt(g32, 0)} ({100 * g32 / peaks['float32']:.0f} %)",
                f"{fmt(f16, 2)} / {fmt(b16, 2)}",
                f"{fmt(g16, 0)} ({100 * g16 / peaks['bf16-mixed']:.0f} %)",
                fmt((f32 + b32) / (f16 + b16), 2),
            ]
        )
    report.add(
        f"## Per-layer kernels, batch {largest}\n\n"
        + markdown_table(
            [
                "layer (weight, input C × H × W)",
                "fp32 fwd / bwd (ms)",
                "fp32 GFLOP/s (of fp32 peak)",
                "bf16 fwd / bwd (ms)",
                "bf16 GFLOP/s (of bf16 peak)",
                "bf16 speed-up",
            ],
            kernel_rows,
        )
        + "\nEach layer alone on the input it gets in the step (captured by a forward hook), "
        "its forward and its backward (input and weight gradients; the first layer's input, "
        "the flow, needs none) timed separately, medians; bf16: the convolutions under bf16 "
        "autocast (including the casts autocast inserts), the decoders in float32 as in the "
        "module. GFLOP/s: FlopCounterMode's count of forward + backward over their time."
    )

    step_ms = {
        name: 1e3 * largest / train_rates[(largest, name)]["lightning"] for name in PRECISIONS
    }
    report.add(bf16_bound(step_ms, kernels, flops - dec_flops, largest, peaks["bf16-mixed"]))

    # 6. The candidates (bare loop).
    cand_rows = []
    fused = VARIANTS["after (fused Adam)"]
    candidates: dict[str, tuple[list[str], dict]] = {
        "float32, for-loop Adam (before)": (VARIANTS["before (for-loop Adam)"], {}),
        "float32, fused Adam (after, the default)": (fused, {}),
        "float32 + channels-last": (fused, {"channels_last": True}),
        "bf16": (fused, {"autocast": True}),
        "bf16 + channels-last": (fused, {"autocast": True, "channels_last": True}),
        "bf16 + first conv in float32": (fused, {"autocast": True, "first_conv": "fp32"}),
        "bf16 + first conv's input padded to 8 channels": (
            fused,
            {"autocast": True, "first_conv": "pad8"},
        ),
    }
    for batch_size, steps in sizes:
        batches = make_batches(samples, batch_size)
        rates = median_of(
            {
                name: partial(bare_rate, base + ov, batches, args.warmup, steps, **opt)
                for name, (ov, opt) in candidates.items()
            },
            args.candidate_repeats,
        )
        if not args.no_compile and batch_size == largest:
            # Once: every build compiles anew (tens of seconds), during its first steps, which
            # are left out of the rate as warm-up.
            for name, opt in (
                ("float32 + torch.compile(net)", {}),
                ("bf16 + torch.compile(net)", {"autocast": True}),
            ):
                rates[name] = bare_rate(
                    base + fused, batches, args.warmup + 10, steps, compile_net=True, **opt
                )
        ref = rates["float32, fused Adam (after, the default)"]
        ref_bf16 = rates["bf16"]
        for name, r in rates.items():
            rel = fmt(r / ref_bf16, 2) if name.startswith("bf16") else "-"
            cand_rows.append([batch_size, name, fmt(r, 1), fmt(r / ref, 2), rel])
    report.add(
        "## Candidate speed-ups of the training step (bare loop)\n\n"
        + markdown_table(["batch", "step", "samples/s", "× float32 fused", "× bf16"], cand_rows)
        + "\n`torch.compile` is timed after its compilation (excluded). The first-conv "
        "candidates are patched onto the network in the bare loop only (the same numbers: "
        "float32 is more precise, zero-padded channels add zeros)."
    )
    report.write()
    # 7. The convolutions' implementations: a section of its own (--convolutions reruns it).
    path = conv_section(args, base, cfg, samples)
    # 8. The sample cache: a section of its own (--sample-cache reruns it).
    sample_cache_section(args, cfg)
    return path


if __name__ == "__main__":
    main()
