"""The CPU kind every figure is named by (:func:`mfg_lightning.core.machine.cpu_kind`): an AMX
machine and an AVX512-BF16 machine without AMX are different kinds, and the kind falls back through
AVX-512 and AVX2 to the machine name."""

from __future__ import annotations

import platform

import pytest

from mfg_lightning.core import machine

# Flag subsets as /proc/cpuinfo prints them on the three kinds of machine this project runs on
# (an Intel Xeon with AMX, an AMD EPYC with AVX512-BF16 and no AMX, an AVX2-only CPU).
XEON_AMX = "fpu sse4_2 avx avx2 avx512f avx512bw avx512_bf16 amx_bf16 amx_tile amx_int8"
EPYC_ZEN4 = "fpu sse4_2 avx avx2 avx512f avx512bw avx512_bf16 avx512_vnni"
AVX2_ONLY = "fpu sse4_2 avx avx2 fma"


@pytest.mark.parametrize(
    ("flags", "kind"),
    [
        (XEON_AMX, "amx_bf16"),
        (EPYC_ZEN4, "avx512_bf16"),
        ("fpu avx2 avx512f", "avx512"),
        (AVX2_ONLY, "avx2"),
        ("", platform.machine() or "unknown"),
    ],
)
def test_the_cpu_kind_tells_amx_from_avx512_bf16(
    monkeypatch: pytest.MonkeyPatch, flags: str, kind: str
) -> None:
    monkeypatch.setattr(machine, "_cpuinfo", lambda: ("a CPU", frozenset(flags.split())))
    assert machine.cpu_kind() == kind
    # the features line names AMX apart too, so the kind and the description agree
    assert machine.cpu_vector_features()["AMX"] is (kind == "amx_bf16")
