"""No host wait in a training step outside the logging steps, in one process and under DDP.

A real training through the entry point, with every host read of a tensor (``.item()``,
``.tolist()``, ``.cpu()``, ``float()``, ``int()``, ``bool()``) and every collective counted per
step by tests/host_waits.py, in every process, Lightning's loop, the progress bar and the
callbacks included. The run reads the agreed flags and the batch checks' flags as on a GPU (at the
logging steps; a CPU may read them every step, where a read waits for nothing). What must hold:

* a step that is not a logging step makes no read at all, and under DDP exactly one collective:
  the agreement's ``all_reduce`` (DDP's gradient all-reduce runs inside the backward);
* the logging steps do read (the loggers' values), which shows that the counting works;
* under DDP the end of an epoch makes one ``all_reduce`` and one read (the batch checks still
  pending are settled), counted apart.

docs/gpu.md ("What a fast device no longer pays for") gives the same counts.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from conftest import REPO, entry_point_env, run_command

pytestmark = pytest.mark.slow

#: the run: a logging step every 4 steps, epochs of 3 (DDP) or 6 (one process) steps, so that
#: steps follow a logging step within its epoch (where Lightning once re-read the bar's loss)
LOG_EVERY, STEPS = 4, 16


def _train(tmp_path: Path, *extra: str) -> list[dict]:
    out = tmp_path / "waits"
    args = [
        "debug=tiny",
        "trainer.precision=32-true",
        f"trainer.max_steps={STEPS}",
        f"trainer.log_every_n_steps={LOG_EVERY}",
        "trainer.val_check_interval=10",
        "model.image_log_every_n_steps=0",
        "+callbacks.batch_checks.deferred=true",
        "+callbacks.host_waits._target_=host_waits.CountHostWaits",
        f"+callbacks.host_waits.path={out}",
        "+callbacks.host_waits.where=true",
        f"hydra.run.dir={tmp_path / 'run'}",
        *extra,
    ]
    env = entry_point_env(tmp_path, PYTHONPATH=str(REPO / "tests"))
    command = ["python", "-m", "mfg_lightning.train", *args]
    proc = run_command(command, cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return [json.loads(p.read_text()) for p in sorted(out.glob("host_waits_rank*.json"))]


def _totals(counts: dict[str, int]) -> dict[str, int]:
    return {k: v for k, v in counts.items() if " at " not in k}


def _sites(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} ×{v}" for k, v in counts.items() if " at " in k)


#: the first process's counts at a logging step, docs/gpu.md's table: the loggers' values
#: (10 .item()), the deferred counts (2 .tolist()), the progress bar's loss (1 float()); under
#: DDP also the agreed flags (1 .tolist()), last.ckpt's clock (1 broadcast_object_list) and the
#: step's all_reduce
LOGGING_STEP = {
    1: {"item": 10, "tolist": 2, "__float__": 1},
    2: {"item": 10, "tolist": 3, "__float__": 1, "all_reduce": 1, "broadcast_object_list": 1},
}


def _check(ranks: list[dict], world_size: int, per_step: dict[str, int]) -> None:
    assert len(ranks) == world_size
    for rank, result in enumerate(ranks):
        steps = result["steps"]
        logging = [s for s in steps if s.isdigit() and (int(s) + 1) % LOG_EVERY == 0]
        others = [s for s in steps if s.isdigit() and s not in logging]
        assert len(others) >= STEPS // 2, f"rank {rank}: too few steps counted: {sorted(steps)}"
        for s in others:
            got = _totals(steps[s])
            assert got == per_step, (
                f"rank {rank}, step {s} (not a logging step): {got}, expected {per_step}; "
                f"made at {_sites(steps[s])}"
            )
        for s in logging:  # the counter sees the reads the loggers make
            assert steps[s].get("item", 0) > 0, f"rank {rank}, logging step {s}: {steps[s]}"
            if rank == 0:  # what the docs say, exactly
                got = _totals(steps[s])
                assert got == LOGGING_STEP[world_size], (
                    f"logging step {s}: {got}; docs/gpu.md says {LOGGING_STEP[world_size]}; "
                    f"made at {_sites(steps[s])}"
                )
        if world_size > 1:  # the pending batch checks are settled together
            assert _totals(steps["epoch_end"]).get("all_reduce", 0) >= 1


def test_one_process_reads_nothing_outside_the_logging_steps(tmp_path: Path) -> None:
    _check(_train(tmp_path), 1, {})


def test_ddp_makes_one_collective_and_no_read_outside_the_logging_steps(tmp_path: Path) -> None:
    _check(_train(tmp_path, "trainer=ddp"), 2, {"all_reduce": 1})
