"""Freed tensors' memory kept in the process (mfg_lightning.core.host_memory): a training step
of the quick start's network then takes next to no page fault, where it took thousands (a count from
getrusage, whatever the machine's load), and the default training applies it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import REPO

STEPS = """
import resource, sys, torch
from mfg_lightning.models.mfg import MFG
torch.manual_seed(0)
net = MFG(hidden_units=256)
opt = torch.optim.Adam(net.parameters(), lr=1e-4)
flow = torch.randn(16, 2, 48, 128)
def step():
    out = net(flow)
    loss = out.v_t.abs().mean() + out.v_omega.abs().mean() + out.hidden.mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
if sys.argv[1] == "kept":
    from mfg_lightning.core.host_memory import keep_freed_memory
    assert keep_freed_memory()
for _ in range(6):
    step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(6):
    step()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 6)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_kept_memory_takes_no_page_fault_a_step_where_the_default_takes_thousands() -> None:
    """Each in a fresh process (the setting lasts for the process): the steps after a warm-up,
    minor page faults per step."""
    faults = {}
    for how in ("default", "kept"):
        proc = subprocess.run([sys.executable, "-c", STEPS, how], capture_output=True, text=True,
                              cwd=REPO, timeout=300, check=True)  # fmt: skip
        faults[how] = float(proc.stdout.split()[-1])
    assert faults["default"] > 1000, faults
    # (a few hundred at most: the heap may still grow by a fragment after the warm-up)
    assert faults["kept"] < faults["default"] / 10, faults


def test_the_default_training_keeps_freed_memory() -> None:
    from mfg_lightning.core.config import compose

    assert compose("train").keep_freed_memory is True
    assert compose("train_flow").keep_freed_memory is True
