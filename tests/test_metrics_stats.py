"""The one statistics helper (mean, std, RMSE; list states) and the published metric names."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import torch

from mfg_lightning.metrics.stats import RENAMED, MetricValues, cat_state, summary


def test_summary_is_numpy_s_mean_std_and_rmse() -> None:
    values = np.random.default_rng(0).gamma(2.0, 0.01, size=37)
    for correction in (0, 1):
        out = summary(torch.from_numpy(values).float(), correction=correction)
        assert all(v.dtype == torch.float64 for v in out.values())
        x = values.astype(np.float32).astype(np.float64)  # the float32 input, in float64
        assert out["mean"].item() == pytest.approx(x.mean(), rel=1e-12)
        assert out["std"].item() == pytest.approx(x.std(ddof=correction), rel=1e-12)
        assert out["rmse"].item() == pytest.approx(math.sqrt(np.mean(x**2)), rel=1e-12)


def test_summary_of_too_few_values_is_nan_not_an_error() -> None:
    assert all(math.isnan(v.item()) for v in summary(torch.zeros(0)).values())
    one = summary(torch.tensor([2.0]), correction=1)
    assert one["mean"].item() == 2.0 and one["rmse"].item() == 2.0 and math.isnan(one["std"])
    assert summary(torch.tensor([2.0]))["std"].item() == 0.0


def test_cat_state() -> None:
    assert cat_state([]).shape == (0,) and cat_state([]).dtype == torch.float64
    parts = [torch.arange(3.0), torch.arange(2.0)]
    assert cat_state(parts).tolist() == [0.0, 1.0, 2.0, 0.0, 1.0]
    assert cat_state(torch.ones(2)).tolist() == [1.0, 1.0]  # already synced


def test_metric_values_lists_published_names_and_reads_earlier_ones() -> None:
    values = MetricValues(rpe_trans=1.0, drift_t_err=2.0)
    assert list(values) == ["rpe_trans", "drift_t_err"] and len(values) == 2
    assert values["trans"] == 1.0 and values["t_err"] == 2.0 and "trans" in values
    assert "rot" not in values and values.get("rot", 3.0) == 3.0
    with pytest.raises(KeyError):
        values["rot"]
    again = pickle.loads(pickle.dumps(values))
    assert type(again) is MetricValues and again["t_err"] == 2.0
    # Every earlier name maps to a published one, never to another earlier name.
    assert not set(RENAMED.values()) & set(RENAMED)
