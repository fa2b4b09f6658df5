"""This machine measured on purpose (mfg_lightning.run.machine_profile, python -m
mfg_lightning.measure): the decision rule against load, a starved measurement keeping the
defaults, and the command printing the table and this CPU kind's row of conf/cpu_defaults.yaml.
No training run measures anything (tests/test_run_choices.py)."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import pytest
import torch
import yaml

from conftest import TINY_TRAINING, run_module
from mfg_lightning.core.machine import cpu_kind
from mfg_lightning.models.conv import switchable_layers
from mfg_lightning.models.mfg import MFG
from mfg_lightning.run import machine_profile
from mfg_lightning.run.machine_profile import (
    CONV_MARGIN,
    MAX_SPREAD,
    clearly_faster,
    measure,
    measure_convolutions,
    spread,
    time_interleaved,
)

SMALL = dict(height=16, width=32, hidden_units=8, channels=(4, 4, 4, 4, 4))


def test_a_candidate_replaces_the_default_only_if_faster_in_every_round_by_the_margin() -> None:
    native = [10.0, 10.0, 10.0, 10.0, 10.0]
    assert clearly_faster({"native": native, "im2col": [8.0] * 5}, "native", 0.05) == "im2col"
    # Faster at its best and in 4 of 5 rounds: one round slower is load or a tie, not a win.
    four = [8.0, 8.0, 8.0, 8.0, 10.5]
    assert clearly_faster({"native": native, "im2col": four}, "native", 0.05) == "native"
    # Faster in every round but within the margin.
    assert clearly_faster({"native": native, "im2col": [9.7] * 5}, "native", 0.05) == "native"
    # Given up after the first round (one time only): never chosen.
    assert clearly_faster({"native": native, "im2col": [1.0]}, "native", 0.05) == "native"
    # Faster in every round and at its best by the margin, but two of the default's rounds over
    # 2.5× its best: the load changed while they ran, and a close call says little (two of the
    # candidate's rounds within the margin of the default's best). One slow round is jitter.
    unsteady = [10.0, 30.0, 12.0, 25.0, 11.0]
    close = [9.0, 9.0, 9.7, 9.8, 9.0]
    assert clearly_faster({"native": unsteady, "im2col": close}, "native", 0.05) == "native"
    jitter = [10.0, 30.0, 12.0, 10.5, 11.0]
    assert clearly_faster({"native": jitter, "im2col": close}, "native", 0.05) == "im2col"
    # A clear call over unsteady rounds: all the candidate's rounds but one beat the default's
    # best (load only adds time), as the deepest layer's im2col did at batch 16 in bfloat16.
    loaded = [41.9, 64.1, 45.0, 63.5, 44.2]
    assert spread(loaded) > MAX_SPREAD  # unsteady: the best-against-best test alone keeps native
    clear = [18.2, 18.9, 24.9, 19.5, 33.0]
    assert clearly_faster({"native": loaded, "im2col": clear}, "native", 0.05) == "im2col"
    # ... but not one slower than the default in any round.
    assert clearly_faster({"native": loaded, "im2col": [*clear[:4], 45.0]}, "native", 0.05) == (
        "native"
    )
    # Of two clear winners, the faster.
    two = {"native": native, "im2col": [8.0] * 5, "channels_last": [7.0] * 5}
    assert clearly_faster(two, "native", 0.05) == "channels_last"


def test_load_that_follows_the_running_order_cannot_pick_the_slower_kernel(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Load that always hits whichever candidate runs first in a round (another process's
    periodic work lining up with the rounds) made the first candidate look slow every time.
    The rounds rotate the order, so the truly slower channels-last (12 ms against native's
    10 ms) is the first one in some rounds and loses there: native stays."""
    order: list[str] = []
    true_ms = {"native": 10.0, "channels_last": 12.0}
    clock = {"now": 0.0}

    def run(name: str) -> None:
        first_in_round = len(order) % 2 == 0
        order.append(name)
        clock["now"] += true_ms[name] + (15.0 if first_in_round else 0.0)

    candidates = {name: (lambda n=name: run(n)) for name in true_ms}
    with monkeypatch.context() as patch:  # a clock of the fake load's milliseconds
        patch.setattr(machine_profile.time, "perf_counter", lambda: clock["now"])
        times = time_interleaved(candidates, rounds=5)
    assert order[:2] == ["native", "channels_last"] and order[2:4] == ["channels_last", "native"]
    # Without rotation native would be first every round: 25 ms against 12, a "clear" win.
    assert clearly_faster(times, "native", CONV_MARGIN) == "native"


def test_a_busy_thread_beside_the_measurement_never_picks_a_kernel_slower_than_native() -> None:
    """A real measurement of a small network's convolutions, quiet and then with a thread
    beside it that loads the cores in bursts (torch matrix products, on and off): every layer
    the busy measurement gives to another kernel than native is one the quiet measurement found
    faster than native. (The old rule, the best of 3 per candidate in a fixed order, picked
    channels-last at 21.5 ms against native's 1.4 ms on a loaded machine.)"""
    net = MFG(height=48, width=128, hidden_units=32, channels=(8, 16, 16, 32, 32))
    shape = (4, 2, 48, 128)
    quiet = measure_convolutions(net, shape, torch.float32, rounds=5)
    stop = threading.Event()

    def bursts() -> None:
        a = torch.randn(384, 384)
        while not stop.is_set():
            end = time.perf_counter() + 0.004
            while time.perf_counter() < end:
                a = (a @ a).clamp_(-1, 1)
            time.sleep(0.003)

    threads = [threading.Thread(target=bursts, daemon=True) for _ in range(2)]
    for thread in threads:
        thread.start()
    try:
        busy = measure_convolutions(net, shape, torch.float32, rounds=5)
    finally:
        stop.set()
        for thread in threads:
            thread.join()
    assert busy.keys() == quiet.keys()
    for name, entry in busy.items():
        choice, ms = entry["choice"], quiet[name]["ms"]
        assert choice == "native" or ms[choice] < ms["native"], (name, entry, quiet[name])


def test_a_starved_measurement_records_the_defaults_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Less CPU time than ``min_cpu_share`` of the threads' (here a share no process reaches):
    every convolution native, float32, the measurement marked disturbed, and a warning that says
    to measure again."""

    def build(conv_impl):
        return MFG(**SMALL, conv_impl=conv_impl)

    shape, threads = (2, 2, SMALL["height"], SMALL["width"]), torch.get_num_threads()
    with caplog.at_level(logging.WARNING):
        found = measure(build, shape, ["float32", "bfloat16"], threads, rounds=1,
                        min_cpu_share=10.0)  # fmt: skip
    assert found.disturbed and found.precision == "32-true"
    assert found.kernels("float32") == found.kernels("bfloat16") == "native"
    assert "measure again on a quiet machine" in caplog.text
    assert found.step_ms.keys() == {"32-true", "bf16-mixed"}


def test_the_measure_command_prints_the_table_and_writes_this_kinds_row(tmp_path: Path) -> None:
    """``python -m mfg_lightning.measure`` measures on purpose, with a progress line per part,
    prints every layer, the precision and this CPU kind's row, and writes the row where it is
    told (by default conf/local/cpu_defaults.yaml, which training runs read); another kind's
    row in that file is kept."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    table = tmp_path / "cpu_defaults.yaml"
    table.write_text("other_kind: {precision: 32-true}\n")
    overrides = [o for o in TINY_TRAINING if not o.startswith(("logger", "callbacks"))]
    proc = run_module("mfg_lightning.measure", *overrides, f"write_row_to={table}",
                      f"hydra.run.dir={tmp_path / 'm'}", cwd=tmp_path)  # fmt: skip
    assert "measuring convolutions in float32 at batch 2 ..." in proc.stdout
    assert "| float32 | `encoder.14` |" in proc.stdout and "precision=auto: " in proc.stdout
    assert f"written to {table}" in proc.stdout and f"{cpu_kind()}:" in proc.stdout
    rows = yaml.safe_load(table.read_text())
    assert rows["other_kind"] == {"precision": "32-true"}
    row = rows[cpu_kind()]
    assert row["precision"] in ("32-true", "bf16-mixed") and row["batch"] == 2
    net = instantiate(compose("train", [*overrides, "paths.output_dir=x"]).model.net)
    assert row["net"]["channels"] == [8, 8, 16, 16, 32]
    for kernels in row["conv_impl"].values():
        assert kernels == "native" or len(kernels) == len(list(switchable_layers(net)))
