"""The egomotion basis analysis: preferred motions of known bases, checkpoint loading, and the
command line on a real tiny training."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from conftest import run_module
from mfg_lightning.analysis.basis import (
    SELECTIVITY_COLUMNS,
    decoder_norms,
    population_statistics,
    preferred_motions,
    selectivity_rows,
)
from mfg_lightning.analysis.basis_report import example_indices
from mfg_lightning.core import geometry
from mfg_lightning.models.mfg import MFG

PNGS = (
    "basis_translational.png",
    "basis_rotational.png",
    "selectivity_3d.png",
    "examples.png",
    "active_units_histogram.png",
    "unit_firing.png",
)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def _known_basis(
    height: int = 16, width: int = 24, units: int = 6
) -> tuple[MFG, torch.Tensor, torch.Tensor, torch.Tensor]:
    """An MFG whose unit j decodes exactly to the fields of a known motion (t_j, ω_j)."""
    K = torch.tensor([20.0, 22.0, 11.5, 7.5])
    g = torch.Generator().manual_seed(0)
    t = torch.randn(units, 3, generator=g)
    w = 0.01 * torch.randn(units, 3, generator=g)
    # decoder_scale=1: the columns are the fields at the input grid. (At 0.5 they are upsampled
    # bilinearly, which is not exact for the quadratic rotational field.)
    net = MFG(
        height=height,
        width=width,
        hidden_units=units,
        channels=[4, 4, 4, 4, 4],
        decoder_scale=1.0,
    )
    with torch.no_grad():
        net.decoder_t.weight.copy_(geometry.translational_field(t, K, height, width).flatten(1).T)
        net.decoder_omega.weight.copy_(geometry.rotational_field(w, K, height, width).flatten(1).T)
    return net, K, t, w


def test_known_basis_fields_recover_their_motions() -> None:
    net, K, t, w = _known_basis()
    t_hat, w_hat = preferred_motions(net, K)
    torch.testing.assert_close(t_hat, t.double(), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(w_hat, w.double(), atol=1e-7, rtol=1e-5)
    # a subset, in a given order
    t_sub, w_sub = preferred_motions(net, K, [4, 1])
    torch.testing.assert_close(t_sub, t[[4, 1]].double(), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(w_sub, w[[4, 1]].double(), atol=1e-7, rtol=1e-5)


def test_selectivity_rows_are_ordered_by_decoder_norm() -> None:
    net, K, t, _ = _known_basis()
    with torch.no_grad():  # make unit 3 the largest and unit 0 the smallest
        net.decoder_t.weight[:, 3] *= 50.0
        net.decoder_omega.weight[:, 0] *= 0.0
        net.decoder_t.weight[:, 0] *= 1e-3
    rows = selectivity_rows(net, K, n_units=4)
    assert [list(r) for r in rows] == [list(SELECTIVITY_COLUMNS)] * 4
    norms = decoder_norms(net)
    assert rows[0]["unit"] == 3
    assert 0 not in [r["unit"] for r in rows]
    assert [r["norm"] for r in rows] == sorted(
        (float(norms[r["unit"]]) for r in rows), reverse=True
    )
    # the preferred translation scales with the column (activation 1 of a 50× column)
    assert rows[0]["tx"] == pytest.approx(50.0 * float(t[3, 0]), rel=1e-4)
    expected = math.sqrt(
        float(
            net.decoder_t.weight[:, 3].detach().square().sum()
            + net.decoder_omega.weight[:, 3].detach().square().sum()
        )
    )
    assert rows[0]["norm"] == pytest.approx(expected, rel=1e-6)


def test_population_statistics_count_active_units() -> None:
    net, *_ = _known_basis()
    flow = torch.randn(5, 2, 16, 24)
    batch = {
        "flow": flow,
        "flow_valid": torch.ones(5, 16, 24, dtype=torch.bool),
        "sample_id": [f"s{i}" for i in range(5)],
    }
    stats = population_statistics(net, [batch, None, batch], max_batches=2)
    hidden, _ = net.encode(flow)
    active = (hidden > 0).sum(1)
    assert stats.n_inputs == 5  # the None batch (all samples skipped) counts nothing
    assert stats.active_per_input.tolist() == active.tolist()
    assert stats.firing_counts.tolist() == (hidden > 0).sum(0).tolist()
    summary = stats.summary()
    assert summary["active_units_mean"] == pytest.approx(float(active.float().mean()))
    assert summary["units_never_active"] == int(((hidden > 0).sum(0) == 0).sum())


def test_example_indices_are_spread_over_the_split() -> None:
    assert example_indices(11, 4) == [0, 3, 7, 10]
    assert example_indices(2, 4) == [0, 1]
    assert example_indices(0, 4) == []


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("analyze")
    run = tmp / "run"
    run_module("mfg_lightning.train", "debug=tiny", f"hydra.run.dir={run}", cwd=tmp)
    return run


@pytest.mark.slow
def test_analyze_basis_on_a_trained_checkpoint(tiny_run: Path) -> None:
    out = tiny_run.parent / "basis"
    ckpt = tiny_run / "checkpoints" / "last.ckpt"
    run_module(
        "mfg_lightning.analyze_basis",
        f"ckpt_path={ckpt}",
        "n_units=20",
        "n_examples=3",
        f"out_dir={out}",
        f"hydra.run.dir={tiny_run.parent / 'analyze_run'}",
        cwd=tiny_run.parent,
    )
    rows = _rows(out / "basis_selectivity.csv")
    assert len(rows) == 20
    assert list(rows[0]) == list(SELECTIVITY_COLUMNS)
    assert len({r["unit"] for r in rows}) == 20
    norms = [float(r["norm"]) for r in rows]
    assert norms == sorted(norms, reverse=True)
    for r in rows:
        assert all(math.isfinite(float(r[c])) for c in SELECTIVITY_COLUMNS)
    for name in PNGS:
        assert (out / name).read_bytes()[:4] == b"\x89PNG", name
    firing = _rows(out / "unit_firing.csv")
    assert len(firing) == 64  # every unit of the tiny model
    assert all(0.0 <= float(r["firing_rate"]) <= 1.0 for r in firing)
    summary = json.loads((out / "summary.json").read_text())
    pop = summary["population"]
    per_input = _rows(out / "active_units_per_input.csv")
    assert pop["n_inputs"] == len(per_input) > 0
    assert 0 <= pop["active_units_mean"] <= 64
    assert pop["active_units_mean"] == pytest.approx(
        sum(int(r["active_units"]) for r in per_input) / len(per_input)
    )
    assert summary["model"] == {**summary["model"], "hidden_units": 64, "height": 32, "width": 64}
    assert len(summary["examples"]) == 3
    # the intrinsics come from the dataset's samples at the model's resolution
    assert summary["intrinsics"]["cx"] < 64 and summary["intrinsics"]["cy"] < 32


@pytest.mark.slow
def test_analyze_basis_with_a_dataset_of_another_resolution_is_a_clear_error(
    tiny_run: Path,
) -> None:
    ckpt = tiny_run / "checkpoints" / "last.ckpt"
    proc = run_module(
        "mfg_lightning.analyze_basis",
        f"ckpt_path={ckpt}",
        "dataset=synthetic",  # the quick-start resolution, 48×128
        f"hydra.run.dir={tiny_run.parent / 'wrong'}",
        cwd=tiny_run.parent,
        check=False,
    )
    assert proc.returncode != 0
    message = proc.stderr + proc.stdout
    assert str(ckpt) in message
    assert "hidden_units=64, input 32×64" in message and "48×128" in message
    assert "dataset.height=32 dataset.width=64" in message
