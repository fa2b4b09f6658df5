"""What the CPU is: its model name and the vector instruction sets that set the speed of every
CPU kernel (oneDNN picks its convolution and GEMM kernels by them).

Read from ``/proc/cpuinfo`` (Linux); elsewhere the model is what :mod:`platform` knows and no
flag is reported. Kept free of torch so that light tools and the benchmarks' headers can use it.
"""

from __future__ import annotations

import os
import platform
from functools import cache
from pathlib import Path

#: The vector features reported, by the ``/proc/cpuinfo`` flag that says the CPU has them.
VECTOR_FEATURES: dict[str, str] = {
    "AVX2": "avx2",
    "AVX-512": "avx512f",
    "AVX512-BF16": "avx512_bf16",
    "AMX": "amx_bf16",
}

#: Environment variables that cap the instruction sets of torch's own kernels, oneDNN's and
#: MKL's below what the CPU has. With ``ATEN_CPU_CAPABILITY``, ``ONEDNN_MAX_CPU_ISA`` and
#: ``MKL_ENABLE_INSTRUCTIONS`` at AVX2 an AVX-512 machine imitates an AVX2 one: its instructions,
#: not its cores or caches. (``DNNL_MAX_CPU_ISA`` is oneDNN's older name.)
ISA_CAP_VARIABLES = (
    "ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "MKL_ENABLE_INSTRUCTIONS"
)  # fmt: skip


def isa_caps() -> dict[str, str]:
    """The :data:`ISA_CAP_VARIABLES` set (non-empty) in this process's environment, e.g.
    ``{"ONEDNN_MAX_CPU_ISA": "AVX2"}``; empty where the kernels run at the CPU's own level."""
    return {k: os.environ[k] for k in ISA_CAP_VARIABLES if os.environ.get(k)}


@cache
def _cpuinfo() -> tuple[str, frozenset[str]]:
    """The first processor's model name and flags from ``/proc/cpuinfo`` (empty where absent)."""
    model, flags = "", frozenset()
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return model, flags
    for line in lines:
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and not model:
            model = value.strip()
        elif key == "flags" and not flags:
            flags = frozenset(value.split())
    return model, flags


def cpu_model() -> str:
    """The CPU's model name (Linux), else what :mod:`platform` knows."""
    return _cpuinfo()[0] or platform.processor() or platform.machine() or "unknown"


def cpu_flags() -> frozenset[str]:
    """Every flag ``/proc/cpuinfo`` gives the first processor (empty where it is unreadable)."""
    return _cpuinfo()[1]


def cpu_vector_features() -> dict[str, bool]:
    """Which of :data:`VECTOR_FEATURES` the CPU has, e.g. ``{"AVX2": True, "AVX-512": False,
    "AVX512-BF16": False, "AMX": False}`` (all False where ``/proc/cpuinfo`` is unreadable)."""
    flags = _cpuinfo()[1]
    return {name: flag in flags for name, flag in VECTOR_FEATURES.items()}


def describe_cpu() -> str:
    """One line naming the CPU and its vector features, e.g. ``"AMD EPYC (AVX2 yes, AVX-512 no,
    AVX512-BF16 no, AMX no)"``: what a measured time depends on."""
    features = ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in cpu_vector_features().items())
    return f"{cpu_model()} ({features})"


def cpu_kind() -> str:
    """The CPU's vector kind, which sets the speed of every CPU figure: ``amx_bf16`` (AMX tiles
    beside AVX512-BF16: Intel's Sapphire Rapids and later), ``avx512_bf16`` (AVX-512 with native
    bfloat16 but no AMX, e.g. AMD's Zen 4), ``avx512``, ``avx2``, else the machine name (a
    non-Linux system or another architecture). AMX is named apart because it, not AVX512-BF16,
    gives bf16-mixed its large speed-up (``docs/precision.md`` measures both kinds)."""
    flags = _cpuinfo()[1]
    kinds = (("amx_bf16", "amx_bf16"), ("avx512_bf16", "avx512_bf16"), ("avx512", "avx512f"),
             ("avx2", "avx2"))  # fmt: skip
    for kind, flag in kinds:
        if flag in flags:
            return kind
    return platform.machine() or "unknown"


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity (what ``taskset``, cgroups' cpusets
    and SLURM's ``--cpus-per-task`` leave it), else every core the system reports; at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux: no affinity to read
        return max(1, os.cpu_count() or 1)


def loader_workers(most: int, processes: object = 1) -> int:
    """Loader workers per training process: at most ``most``, and no more than the usable cores
    leave each of ``processes`` training processes beside itself (``cores // processes - 1``).

    Args:
        most: the most workers wanted per process.
        processes: training processes on this machine (``trainer.devices``: a count, a list
            or ``"0,1"`` of device indices; ``"auto"`` or -1: every visible GPU). Inside a task
            ``srun`` started (``SLURM_PROCID``), 1: its cores are its own.
    """
    if most < 0:
        raise ValueError(f"loader_workers: the most workers must be >= 0, got {most}")
    if os.environ.get("SLURM_PROCID") is not None:
        n = 1  # a task srun started: its cores (--cpus-per-task) are its own already
    elif not isinstance(processes, str) and hasattr(processes, "__len__"):
        n = len(processes)  # type: ignore[arg-type]  # device indices, e.g. [0, 1]
    elif isinstance(processes, str) and "," in processes:
        n = len([p for p in processes.split(",") if p.strip()])  # "0,1"
    else:
        try:
            n = int(processes)  # type: ignore[call-overload]
        except (TypeError, ValueError):
            n = -1
    if n < 1:  # "auto", -1: every visible GPU
        import torch  # here only: this module stays free of torch for the light tools

        n = max(1, torch.cuda.device_count()) if torch.cuda.is_available() else 1
    return max(0, min(most, usable_cores() // n - 1))
