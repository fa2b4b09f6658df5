"""This machine measured on purpose, for ``python -m mfg_lightning.measure``: what
``trainer.precision=auto`` and ``model.net.conv_impl=auto`` should be on a CPU of its kind.

The result is a row of the table a training run reads (``conf/cpu_defaults.yaml``,
:mod:`mfg_lightning.run.run_choices`); no training run times anything.

How, so that load cannot pick a slow kernel (:func:`time_interleaved`, :func:`clearly_faster`):
the candidates are timed in interleaved rounds (the order rotated each round) after a warm-up.
A candidate replaces the default (``native``, ``32-true``) only if it beats the default's best by
a margin, with steady rounds or all its rounds but one, *and* it is faster than the default in
every round, each against the default's time of the same round. If the process got less than
:data:`BUSY_CPU_SHARE` of its threads' CPU time, other work had the cores: every choice is the
default, and the command says to measure again on a quiet machine.

The precision compares whole training steps of the network (forward, a loss over both fields
and the hidden units, backward) in float32 and under bfloat16 autocast, each with its own
measured convolutions. bfloat16 is measured only where the CPU computes it natively
(AVX512-BF16 or AMX, :func:`~mfg_lightning.run.precision.cpu_has_native_bf16`).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn

from mfg_lightning.core.host_memory import freed_memory_kept
from mfg_lightning.core.machine import describe_cpu
from mfg_lightning.models.conv import SwitchableConv2d, layer_inputs, switchable_layers
from mfg_lightning.run.precision import PRECISION_AUTO, cpu_has_native_bf16
from mfg_lightning.run.run_choices import needs_bf16, net_geometry

log = logging.getLogger(__name__)

#: Timed rounds per candidate, after one warm-up round.
ROUNDS = 5
#: A convolution replaces ``native`` only this much faster (fraction of native's best time).
CONV_MARGIN = 0.05
#: bf16-mixed replaces float32 only this much faster per training step: below it the speed does
#: not pay for the lower precision's rounding.
PRECISION_MARGIN = 0.10
#: Below this share of its threads' CPU time while timing, the process was starved by other work
#: (seen on 2 cores: a nice-19 run beside a 2-thread job got 4 %, a quiet benchmark 88 %).
BUSY_CPU_SHARE = 0.3
#: Rounds whose second-slowest is over this many times their best (:func:`spread`) are unsteady:
#: a close call (best against best) counts only where the candidate's and the default's rounds
#: are steady (:func:`clearly_faster`). On a quiet 2-core machine (bench/results/throughput.md)
#: 7 of 144 timings of the quick start's network at batches 1, 16 and 32 were, all under 8 ms.
MAX_SPREAD = 1.5
#: A convolution this many times slower than native in the first timed round is not timed again.
GIVE_UP = 2.0
#: The dtypes a convolution is measured in, by name.
DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
#: The precision each measured dtype trains under.
PRECISION_OF = {"float32": "32-true", "bfloat16": "bf16-mixed"}


def time_interleaved(
    candidates: Mapping[str, Callable[[], None]], rounds: int = ROUNDS, give_up: float | None = None
) -> dict[str, list[float]]:
    """Seconds of each candidate in each of ``rounds`` rounds, after one untimed warm-up round
    (oneDNN builds its primitives, the allocator warms). Every round runs every candidate once,
    in an order rotated by one each round, so a change of the machine's load reaches them alike
    and no candidate always runs first. With ``give_up``, a candidate more than ``give_up``
    times slower than the first (the default) in the first timed round is not timed again: it
    cannot win, and it is the longest to time (im2col on a large map)."""
    names = list(candidates)
    times: dict[str, list[float]] = {name: [] for name in names}
    timing = list(names)
    for round_ in range(rounds + 1):
        shift = round_ % len(timing)
        for name in timing[shift:] + timing[:shift]:
            start = time.perf_counter()
            candidates[name]()
            if round_:
                times[name].append(time.perf_counter() - start)
        if round_ == 1 and give_up is not None:
            limit = give_up * times[names[0]][0]
            timing = [n for n in timing if n == names[0] or times[n][0] <= limit]
    return times


def spread(times: Sequence[float]) -> float:
    """How unsteady the rounds of one candidate were: the second-slowest over the best (the
    slowest over the best with under 3 rounds). One slow round is the system's jitter, seen on a
    quiet machine; two are a change of load."""
    ordered = sorted(times)
    return (ordered[-2] if len(ordered) >= 3 else ordered[-1]) / ordered[0]


def clearly_faster(
    times: Mapping[str, Sequence[float]],
    default: str,
    margin: float,
    max_spread: float = MAX_SPREAD,
) -> str:
    """The choice among timed candidates (:func:`time_interleaved`): the fastest by its best
    round among those that were faster than ``default`` in every round they ran, each against
    ``default``'s time of the same round (a candidate given up after one round is slower), and
    that beat ``default`` by more than ``margin`` in one of two ways:

    * *steady*: its best beats the default's best, and neither's rounds spread over more than
      ``max_spread`` (:func:`spread`);
    * *dominant*: its second-slowest round beats the default's best, however the rounds spread.

    ``default`` where none does. Load only ever adds time, so a default's best is at most its
    quiet time, and a candidate whose rounds but one beat that best by the margin is faster
    whatever the load did: unsteady rounds stop a close call (the load may have hit the default
    in its best round too), not a clear one. (On 2 loaded cores the deepest layer's im2col ran
    18.2 ms at batch 16 in bfloat16 against native's best of 41.9, faster in every round, and
    the spread rule alone kept native: native's rounds spread 1.53.)"""
    base = times[default]

    def steady(t: Sequence[float]) -> bool:
        return spread(t) <= max_spread

    def second_slowest(t: Sequence[float]) -> float:
        return sorted(t)[-2] if len(t) >= 3 else max(t)

    bound = (1.0 - margin) * min(base)
    winners = [
        name for name, t in times.items()
        if name != default
        and len(t) == len(base)
        and all(a < b for a, b in zip(t, base, strict=True))
        and ((min(t) < bound and steady(t) and steady(base)) or second_slowest(t) < bound)
    ]  # fmt: skip
    return min(winners, key=lambda name: min(times[name])) if winners else default


def _autocast(dtype: torch.dtype) -> torch.autocast:
    return torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32)


def _layer_step(layer: SwitchableConv2d, impl: str, x: Tensor, dtype: torch.dtype) -> Callable:
    """One forward + backward of ``layer`` (a copy's weights) as ``impl`` on ``x``."""

    def step() -> None:
        layer.impl = impl
        with _autocast(dtype):
            y = layer(x)
        y.backward(torch.ones_like(y))
        for tensor in (x, layer.weight, layer.bias):
            if tensor is not None:
                tensor.grad = None  # as zero_grad: the next backward writes, not adds

    return step


def measure_convolutions(
    net: nn.Module, flow_shape: tuple[int, ...], dtype: torch.dtype, rounds: int = ROUNDS
) -> dict[str, dict[str, Any]]:
    """Each convolution of ``net`` timed alone as each of its candidates, on the input it gets
    in a training step on ``flow_shape`` in ``dtype``: ``{layer name: {"ms": {impl: best
    milliseconds}, "spread": {impl: :func:`spread`}, "choice": impl}}`` in module order
    (:func:`clearly_faster`, default ``native``). On copies of the layers: ``net`` is
    untouched."""
    import copy

    layers = dict(switchable_layers(net))
    inputs = layer_inputs(net, layers, flow_shape, dtype)
    generator = torch.Generator().manual_seed(0)
    result: dict[str, dict[str, Any]] = {}
    for name, layer in layers.items():
        if name not in inputs:  # a layer the forward does not reach: nothing to choose
            result[name] = {"ms": {}, "choice": "native"}
            continue
        given = inputs[name]
        probe = copy.deepcopy(layer)
        x = torch.randn(given.shape, generator=generator).to(given.dtype)
        x.requires_grad_(given.requires_grad)
        # native first: the default every other candidate is compared with
        steps = {impl: _layer_step(probe, impl, x, dtype) for impl in layer.candidates()}
        times = time_interleaved(steps, rounds, give_up=GIVE_UP)
        result[name] = {
            "ms": {impl: round(1e3 * min(t), 4) for impl, t in times.items()},
            # the second-slowest round over the best: how steady the machine was while timing
            "spread": {impl: round(spread(t), 3) for impl, t in times.items()},
            "choice": clearly_faster(times, "native", CONV_MARGIN),
        }
    return result


def _net_step(net: nn.Module, flow: Tensor, dtype: torch.dtype) -> Callable:
    """One training step of the network alone: forward (the encoder under autocast in a low
    ``dtype``, the decoders in float32 as the model runs them), a loss over both fields and the
    hidden units, backward."""

    def step() -> None:
        with _autocast(dtype):
            out = net(flow)
        loss = sum(t.float().abs().mean() for t in (out.v_t, out.v_omega, out.hidden))
        loss.backward()
        net.zero_grad(set_to_none=True)

    return step


@dataclass
class Measurement:
    """One measurement of this machine (:func:`measure`).

    Attributes:
        conv: per dtype name, ``{layer name: {"ms": {impl: ms}, "spread": {...}, "choice": impl}}``.
        step_ms: the network's training step per precision, best milliseconds.
        precision: ``auto``'s choice (``32-true`` or ``bf16-mixed``).
        disturbed: the process was starved while timing: every choice is the default.
        seconds: how long measuring took.
    """

    conv: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)
    step_ms: dict[str, float] = field(default_factory=dict)
    precision: str = "32-true"
    disturbed: bool = False
    seconds: float = 0.0

    def kernels(self, dtype: str) -> list[str] | str:
        """The implementation of every convolution in module order, measured in ``dtype``
        (``"native"`` where every one is)."""
        found = [entry["choice"] for entry in self.conv[dtype].values()]
        return "native" if set(found) <= {"native"} else found

    def table(self) -> str:
        """The measurement as a Markdown table: a row per layer and dtype, then the steps."""
        rows = ["| dtype | layer | native (ms) | im2col (ms) | channels_last (ms) | choice |",
                "|---|---|---:|---:|---:|---|"]  # fmt: skip
        for dtype, layers in self.conv.items():
            for name, entry in layers.items():
                ms = [f"{entry['ms'][i]:.3f}" if i in entry["ms"] else "-"
                      for i in ("native", "im2col", "channels_last")]  # fmt: skip
                rows.append(f"| {dtype} | `{name}` | {' | '.join(ms)} | {entry['choice']} |")
        if self.step_ms:
            rows += ["", "| precision | training step of the network (ms) |", "|---|---:|"]
            rows += [f"| {p} | {ms:.2f} |" for p, ms in self.step_ms.items()]
        note = " (disturbed: the defaults)" if self.disturbed else ""
        return "\n".join([*rows, "", f"precision=auto: {self.precision}{note}"])


@contextmanager
def _threads(threads: int) -> Iterator[None]:
    kept = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(kept)


def measure(
    build_net: Callable[[str | list[str]], nn.Module],
    flow_shape: tuple[int, ...],
    dtypes: Sequence[str],
    threads: int,
    rounds: int = ROUNDS,
    min_cpu_share: float = BUSY_CPU_SHARE,
    progress: Callable[[str], None] | None = None,
) -> Measurement:
    """Measure this machine: the convolutions in each of ``dtypes`` (names of :data:`DTYPES`),
    then, with two dtypes, the network's step in each with its own kernels.

    Args:
        build_net: ``conv_impl`` (one setting or a list per layer) → the network (same seed).
        flow_shape: the training input ``(batch, 2, height, width)``.
        dtypes: ``["float32"]``, ``["bfloat16"]`` or both (then the precision is measured).
        threads: torch threads while timing (those of one training process).
        rounds: timed rounds per candidate.
        min_cpu_share: below this CPU share the measurement counts as disturbed (0: never).
        progress: called with a line before each part (the command prints it).
    """
    say = progress or (lambda line: None)
    found = Measurement()
    start, cpu = time.perf_counter(), time.process_time()
    with _threads(threads), torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)  # the global generator is restored after
        for name in dtypes:
            say(f"convolutions in {name} at batch {flow_shape[0]}")
            found.conv[name] = measure_convolutions(
                build_net("native"), flow_shape, DTYPES[name], rounds
            )
        if len(dtypes) > 1:
            say("a training step of the network per precision")
            flow = torch.randn(flow_shape)
            steps = {PRECISION_OF[n]: _net_step(build_net(found.kernels(n)), flow, DTYPES[n])
                     for n in dtypes}  # fmt: skip
            times = time_interleaved(steps, rounds)
            found.step_ms = {p: round(1e3 * min(t), 3) for p, t in times.items()}
            found.precision = clearly_faster(times, "32-true", PRECISION_MARGIN)
        else:
            found.precision = PRECISION_OF[dtypes[0]]
    found.seconds = round(time.perf_counter() - start, 2)
    share = (time.process_time() - cpu) / max(1e-9, found.seconds * threads)
    if share < min_cpu_share:
        found.disturbed = True
        found.precision = "32-true" if len(dtypes) > 1 else found.precision
        for layers in found.conv.values():
            for entry in layers.values():
                entry["choice"] = "native"
        log.warning(
            "the machine was busy while it was measured (this process got %.0f %% of its %d "
            "threads' CPU time): the defaults (native convolutions, float32 where both were "
            "measured) are kept; measure again on a quiet machine", 100 * share, threads,
        )  # fmt: skip
    return found


def training_threads(trainer_cfg: DictConfig) -> int:
    """The torch threads each training process of ``trainer_cfg`` runs with on a CPU: Lightning
    gives each of several processes ``usable cores // processes`` unless ``OMP_NUM_THREADS`` is
    set; one process keeps this process's count."""
    devices = trainer_cfg.get("devices", "auto")
    processes = int(devices) if str(devices).isdigit() else 1
    if processes > 1 and "OMP_NUM_THREADS" not in os.environ:
        return max(1, len(os.sched_getaffinity(0)) // processes)
    return torch.get_num_threads()


def measure_run(
    cfg: DictConfig, progress: Callable[[str], None] | None = None
) -> tuple[Measurement, dict[str, Any]]:
    """Measure this machine for the training run ``cfg`` describes (its network, batch and
    thread count; both dtypes where ``trainer.precision=auto`` may choose bfloat16). Returns
    the measurement and its row of ``conf/cpu_defaults.yaml``."""
    from hydra.utils import instantiate

    given = str(cfg.trainer.precision)
    if given == PRECISION_AUTO:
        dtypes = ["float32", "bfloat16"] if cpu_has_native_bf16() else ["float32"]
    else:
        dtypes = ["bfloat16"] if needs_bf16(given) else ["float32"]
    plain = OmegaConf.to_container(cfg.model.net, resolve=True)
    batch, threads = int(cfg.dataset.batch_size), training_threads(cfg.trainer)
    # timed as training runs (mfg_lightning.core.host_memory), then set back
    with freed_memory_kept(bool(cfg.get("keep_freed_memory", True))):
        found = measure(
            lambda conv_impl: instantiate({**plain, "conv_impl": conv_impl}),
            (batch, 2, int(plain["height"]), int(plain["width"])),
            dtypes,
            threads,
            progress=progress,
        )
    row = {
        "cpu": f"{describe_cpu()}, {threads} threads, torch {torch.__version__}",
        "measured": f"python -m mfg_lightning.measure, {found.seconds:.0f} s"
        + (", disturbed" if found.disturbed else ""),
        "precision": found.precision,
        "batch": batch,
        "net": net_geometry(plain),
        "conv_impl": {name: found.kernels(name) for name in dtypes},
    }
    return found, row
