"""What a training run may choose by timing, measured once per machine and then fixed:
``trainer.precision=auto`` (float32 or bf16-mixed) and ``model.net.conv_impl=auto`` (each
convolution's implementation, :mod:`mfg_lightning.models.conv`).

Why once: the choices change a run's numbers (the kernels round differently, bfloat16 more so),
so two runs of one config and seed agree only if they choose alike, and timings taken at the
start of every run do not: two runs started together time each other's load. So the machine is
measured once, under a file lock (a run that starts while another measures waits for that
measurement and reads it), and the result is kept in ``<paths.cache_dir>/machine/<digest>.json``,
keyed by everything the answer depends on (:func:`profile_key`: the CPU's model and flags, the
instruction-set caps, torch's and oneDNN's versions, the thread count, the network's geometry and
input, the batch). A training run measures only where no such file exists;
``python -m mfg_lightning.measure`` measures on purpose and prints the table.

How, so that a loaded machine cannot pick a slow kernel (:func:`time_interleaved`,
:func:`clearly_faster`): the candidates are timed in interleaved rounds (the order rotated each
round) after a warm-up; a candidate replaces the default (``native``, ``32-true``) only if its
best time beats the default's best by a margin (with steady rounds, or all its rounds but one
beating that best) *and* it is faster than the default in every round, each against the
default's time of the same round. Load that comes and goes hits the
candidates of a round alike, or makes the rounds disagree, and the default stays. If the
process got less than :data:`BUSY_CPU_SHARE` of its threads' CPU time while timing, other work
had the cores: every choice is the default and the file says the measurement was disturbed
(``python -m mfg_lightning.measure`` on a quiet machine measures again).

The precision compares whole training steps of the network (forward, a loss over both fields
and the hidden units, backward) in float32 and under bfloat16 autocast, each with its own
measured convolutions. bfloat16 is measured only where the CPU computes it natively
(AVX512-BF16 or AMX, :func:`~mfg_lightning.run.precision.cpu_has_native_bf16`); elsewhere
``auto`` is ``32-true`` unmeasured, as on a GPU (where ``conv_impl=auto`` is ``native``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from filelock import FileLock
from torch import Tensor, nn

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.core.machine import cpu_flags, cpu_model, describe_cpu, isa_caps
from mfg_lightning.models.conv import SwitchableConv2d, layer_inputs, switchable_layers
from mfg_lightning.run.precision import PRECISION_AUTO, cpu_has_native_bf16

log = logging.getLogger(__name__)

#: Bumped when what is measured or how it is decided changes: older files are measured again.
PROFILE_VERSION = 6  # 6: a dominant candidate wins over unsteady rounds (clearly_faster)
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
#: are steady, so a change of load while timing keeps the default unless the candidate dominates
#: (:func:`clearly_faster`). Short timings are unsteady on a quiet machine too: there (2 cores,
#: bench/results/throughput.md) 7 of 144 timings of the quick start's network at batches 1, 16
#: and 32 were, all under 8 ms; those layers keep the default, which costs little.
MAX_SPREAD = 1.5
#: A convolution this many times slower than native in the first timed round is not timed again.
GIVE_UP = 2.0
#: The dtypes a convolution is measured in, by name.
DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
#: The precision each measured dtype trains under.
PRECISION_OF = {"float32": "32-true", "bfloat16": "bf16-mixed"}
#: The geometry keys of ``model.net`` that decide the layers' shapes.
NET_GEOMETRY = ("height", "width", "hidden_units", "channels", "kernels", "strides",
                "double_blocks", "decoder_scale")  # fmt: skip


def onednn_version() -> str:
    """oneDNN's version as torch's build reports it (``"3.12.0"``), or ``"unknown"``."""
    found = re.search(r"(?:MKL-DNN|oneDNN) v([0-9][0-9.]*)", torch.__config__.show())
    return found.group(1) if found else "unknown"


def profile_key(net_cfg: Mapping[str, Any], batch: int, threads: int) -> dict[str, Any]:
    """Everything a measured time depends on: the machine (CPU model, a digest of its flags,
    torch's CPU capability, instruction-set caps in the environment, torch's and oneDNN's
    versions), the thread count, the network's geometry and input, and the batch."""
    capability = getattr(torch.backends.cpu, "get_cpu_capability", lambda: "unknown")()
    return {
        "cpu": cpu_model(),
        "cpu_flags": hashlib.sha256(" ".join(sorted(cpu_flags())).encode()).hexdigest()[:16],
        "torch_cpu_capability": capability,
        "isa_caps": isa_caps(),
        "torch": torch.__version__,
        "onednn": onednn_version(),
        "threads": int(threads),
        "net": {k: _plain(net_cfg[k]) for k in NET_GEOMETRY if k in net_cfg},
        "batch": int(batch),
        "version": PROFILE_VERSION,
    }


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, Sequence) and not isinstance(value, str) else value


def profile_path(cache_dir: str | Path, key: Mapping[str, Any]) -> Path:
    """``<cache_dir>/machine/<digest of the key>.json``."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cache_dir).expanduser() / "machine" / f"{digest}.json"


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
class Profile:
    """One machine's measurement (:func:`machine_profile`).

    Attributes:
        key: :func:`profile_key`.
        conv: per dtype name, ``{layer name: {"ms": {impl: ms}, "choice": impl}}``.
        step_ms: the network's training step per precision, best milliseconds.
        step_spread: its :func:`spread`, per precision.
        precision: ``auto``'s choice (``32-true`` or ``bf16-mixed``).
        disturbed: the process was starved while timing: every choice is the default.
        seconds: how long measuring took.
    """

    key: dict[str, Any]
    conv: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)
    step_ms: dict[str, float] = field(default_factory=dict)
    step_spread: dict[str, float] = field(default_factory=dict)
    precision: str = "32-true"
    disturbed: bool = False
    seconds: float = 0.0

    def kernels(self, dtype: str) -> list[str]:
        """The implementation of every convolution in module order, measured in ``dtype``."""
        return [entry["choice"] for entry in self.conv[dtype].values()]

    def table(self) -> str:
        """The measurement as a Markdown table: a row per layer and dtype, then the steps."""
        rows = ["| dtype | layer | native (ms) | im2col (ms) | channels_last (ms) | choice |",
                "|---|---|---:|---:|---:|---|"]  # fmt: skip
        for dtype, layers in self.conv.items():
            for name, entry in layers.items():
                ms = [f"{entry['ms'][i]:.3f}" if i in entry["ms"] else "-"
                      for i in ("native", "im2col", "channels_last")]  # fmt: skip
                rows.append(f"| {dtype} | `{name}` | {' | '.join(ms)} | {entry['choice']} |")
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
    key: Mapping[str, Any],
    dtypes: Sequence[str],
    rounds: int = ROUNDS,
    min_cpu_share: float = BUSY_CPU_SHARE,
    progress: Callable[[str], None] | None = None,
) -> Profile:
    """Measure this machine for ``key``: the convolutions in each of ``dtypes`` (names of
    :data:`DTYPES`), then, with two dtypes, the network's step in each with its own kernels.

    Args:
        build_net: ``conv_impl`` (one setting or a list per layer) → the network (same seed).
        key: :func:`profile_key` (its ``threads`` and ``batch`` are used).
        dtypes: ``["float32"]``, ``["bfloat16"]`` or both (then the precision is measured).
        rounds: timed rounds per candidate.
        min_cpu_share: below this CPU share the measurement counts as disturbed (0: never).
        progress: called with a line before each part (the command prints it).
    """
    say = progress or (lambda line: None)
    profile = Profile(dict(key))
    batch, net_key = int(key["batch"]), key["net"]
    flow_shape = (batch, 2, int(net_key["height"]), int(net_key["width"]))
    start, cpu = time.perf_counter(), time.process_time()
    with _threads(int(key["threads"])), torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)  # the global generator is restored after: a run's seed is intact
        for name in dtypes:
            say(f"convolutions in {name} at batch {batch}")
            profile.conv[name] = measure_convolutions(
                build_net("native"), flow_shape, DTYPES[name], rounds
            )
        if len(dtypes) > 1:
            say("a training step of the network per precision")
            flow = torch.randn(flow_shape)
            steps = {PRECISION_OF[n]: _net_step(build_net(profile.kernels(n)), flow, DTYPES[n])
                     for n in dtypes}  # fmt: skip
            times = time_interleaved(steps, rounds)
            profile.step_ms = {p: round(1e3 * min(t), 3) for p, t in times.items()}
            profile.step_spread = {p: round(spread(t), 3) for p, t in times.items()}
            profile.precision = clearly_faster(times, "32-true", PRECISION_MARGIN)
        else:
            profile.precision = PRECISION_OF[dtypes[0]]
    profile.seconds = round(time.perf_counter() - start, 2)
    spreads = [v for layers in profile.conv.values() for e in layers.values()
               for v in e["spread"].values()] + list(profile.step_spread.values())  # fmt: skip
    unsteady = sum(v > MAX_SPREAD for v in spreads)
    if unsteady:
        log.warning(
            "%d of %d timings were unsteady (two rounds over %.1f× their best: short ones, or "
            "load that changed while they ran): where they decide, the defaults are kept; on a "
            "busy machine `python -m mfg_lightning.measure` measures again once it is quiet",
            unsteady, len(spreads), MAX_SPREAD,
        )  # fmt: skip
    share = (time.process_time() - cpu) / max(1e-9, profile.seconds * int(key["threads"]))
    if share < min_cpu_share:
        profile.disturbed = True
        profile.precision = "32-true" if len(dtypes) > 1 else profile.precision
        for layers in profile.conv.values():
            for entry in layers.values():
                entry["choice"] = "native"
        log.warning(
            "the machine was busy while it was measured (this process got %.0f %% of its %d "
            "threads' CPU time): the defaults (native convolutions, float32 where both were "
            "measured) are recorded; `python -m mfg_lightning.measure` on a quiet machine "
            "measures again", 100 * share, key["threads"],
        )  # fmt: skip
    return profile


def read_profile(path: Path, key: Mapping[str, Any], dtypes: Sequence[str]) -> Profile | None:
    """The profile in ``path`` if it holds ``key`` and every one of ``dtypes`` (and the precision
    where two are needed); None otherwise (absent, another key, unreadable: measured again)."""
    try:
        data = json.loads(path.read_text())
        profile = Profile(**data)
    except FileNotFoundError:
        return None
    except (OSError, ValueError, TypeError) as err:
        log.warning("%s is unreadable (%s): the machine is measured again", path, err)
        return None
    if profile.key != dict(key) or not set(dtypes) <= set(profile.conv):
        return None
    if len(dtypes) > 1 and not profile.step_ms:
        return None
    return profile


def machine_profile(
    cache_dir: str | Path | None,
    key: Mapping[str, Any],
    dtypes: Sequence[str],
    build_net: Callable[[str | list[str]], nn.Module],
    again: bool = False,
    progress: Callable[[str], None] | None = None,
) -> tuple[Profile, bool]:
    """This machine's profile for ``key``: read from ``cache_dir`` or measured (and written)
    under a file lock, so that processes starting together make one measurement. Returns the
    profile and whether it was read rather than measured now.

    Args:
        cache_dir: ``paths.cache_dir``; None: measured every time, nothing kept.
        key, dtypes, build_net, progress: as :func:`measure`.
        again: measure even where a file exists (the command; the file is replaced).
    """
    if cache_dir is None:
        return measure(build_net, key, dtypes, progress=progress), False
    path = profile_path(cache_dir, key)
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(path) + ".lock"):
        found = None if again else read_profile(path, key, dtypes)
        if found is not None:
            return found, True
        old = read_profile(path, key, ())
        missing = [d for d in dtypes if again or old is None or d not in old.conv]
        profile = measure(build_net, key, list(dtypes) if len(dtypes) > 1 else missing,
                          progress=progress)  # fmt: skip
        if old is not None and not again:  # another dtype measured before: kept
            profile.conv = {**old.conv, **profile.conv}
            if not profile.step_ms:
                profile.step_ms, profile.precision = old.step_ms, old.precision
        try:
            atomic_write_text(path, json.dumps(profile.__dict__, indent=1) + "\n")
        except OSError as err:  # a read-only cache: the choice still holds for this run
            log.warning("could not keep the machine's measurement in %s (%s)", path, err)
        return profile, False


def describe(profile: Profile, read: bool, given: str = PRECISION_AUTO) -> str:
    """One log line: where the choice came from and what it is (``given``: the run's
    ``trainer.precision``; only ``auto`` is resolved by the profile, any other value just picks
    the kernels' dtype)."""
    how = "read" if read else f"measured in {profile.seconds:.1f} s"
    choice = (f"precision=auto -> {profile.precision}" if given == PRECISION_AUTO
              else f"precision={given} as given, {'/'.join(profile.conv)} kernels")  # fmt: skip
    return (
        f"machine profile ({how}; {describe_cpu()}, {profile.key['threads']} threads, batch "
        f"{profile.key['batch']}): {choice}{', disturbed: defaults' if profile.disturbed else ''}"
    )


def needs_bf16(precision: str, native_bf16: bool | None = None) -> bool:
    """Whether a run under ``precision`` computes its convolutions in bfloat16 on this CPU:
    a mixed precision where bfloat16 is native (elsewhere it is emulated, and the choice is made
    for float32)."""
    native = cpu_has_native_bf16() if native_bf16 is None else native_bf16
    return str(precision).endswith("-mixed") and native
