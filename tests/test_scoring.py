"""Scoring MFG at several k from one encoder pass (mfg_lightning.analysis.scoring)."""

from __future__ import annotations

import math

import pytest
import torch
from hydra.utils import instantiate
from torch.utils.data import DataLoader

from mfg_lightning.analysis.scoring import Method, mfg_method, mfg_top_k_methods, score_methods
from mfg_lightning.core.config import compose
from mfg_lightning.data.base import collate_samples
from mfg_lightning.data.sample import model_inputs
from mfg_lightning.run.runs import build_model

KS = [1.0, 0.5, 0.1, 0.02]


@pytest.fixture(scope="module")
def tiny() -> tuple[torch.nn.Module, list[dict]]:
    cfg = compose("train", ["debug=tiny", "seed=3"])
    torch.manual_seed(3)
    model = build_model(cfg).eval()
    dm = instantiate(cfg.dataset)
    loader = DataLoader(dm.dataset("test"), batch_size=8, collate_fn=collate_samples)
    return model, list(loader)


def test_shared_encoder_predicts_what_predict_motion_does(tiny) -> None:
    """Every k's motion equals ``model.predict_motion(flow, K, top_k=k)``, and the k differ
    (the units dropped matter), with one encoder pass per batch for all of them."""
    model, batches = tiny
    calls = []
    hook = model.net.encoder.register_forward_hook(lambda *_: calls.append(1))
    try:
        predicts = mfg_top_k_methods(model, KS)
        batch = batches[0]
        got = [p(batch) for p in predicts]
        assert len(calls) == 1
        flow = model_inputs(batch).flow
        with torch.inference_mode():
            want = [model.predict_motion(flow, batch["intrinsics"], top_k=k)[:2] for k in KS]
    finally:
        hook.remove()
    for k, (t, w), (t0, w0) in zip(KS, got, want, strict=True):
        assert t.shape == w.shape == (flow.shape[0], 3)
        torch.testing.assert_close(t, t0, rtol=0, atol=0, msg=f"t at k={k}")
        torch.testing.assert_close(w, w0, rtol=0, atol=0, msg=f"ω at k={k}")
    assert not torch.allclose(got[0][0], got[-1][0])


def test_scoring_several_k_at_once_matches_one_at_a_time(tiny) -> None:
    model, batches = tiny
    together = [Method(f"k={k}", p) for k, p in zip(KS, mfg_top_k_methods(model, KS), strict=True)]
    score_methods(together, batches, warm_up=False)
    for k, m in zip(KS, together, strict=True):
        alone = Method(f"k={k}", mfg_method(model, k))
        score_methods([alone], batches, warm_up=False)
        assert alone.frames == m.frames == sum(b["flow"].shape[0] for b in batches)
        assert alone.trans_err == m.trans_err and alone.rot_err == m.rot_err
        a, b = alone.evaluator.compute().metrics, m.evaluator.compute().metrics
        assert a.keys() == b.keys() and math.isfinite(a["ate"]) and math.isfinite(a["rpe_trans"]), k
        for key in a:  # (NaN where a metric is undefined on this tiny split: NaN in both)
            assert a[key] == b[key] or (math.isnan(a[key]) and math.isnan(b[key])), (k, key)


def test_scoring_refuses_a_model_in_training_mode(tiny) -> None:
    model, batches = tiny
    model.train()
    try:
        with pytest.raises(ValueError, match="evaluation mode"):
            mfg_method(model, 0.1)(batches[0])
    finally:
        model.eval()


def test_a_top_k_that_is_not_a_fraction_is_refused_where_it_is_read(tiny) -> None:
    model, _ = tiny
    for bad in (None, 0.0, 1.5):
        with pytest.raises(ValueError, match="top_k must be a fraction in"):
            mfg_method(model, bad)


def test_scoring_refuses_flow_of_another_size(tiny) -> None:
    model, batches = tiny
    batch = {**batches[0]}
    batch["flow"] = batch["flow"][..., :-2]
    batch["flow_valid"] = batch["flow_valid"][..., :-2]
    with pytest.raises(ValueError, match="MFG was built for 32×64 flow"):
        mfg_method(model, 1.0)(batch)
