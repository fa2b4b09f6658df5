"""The MFG network: shapes, non-negativity, top-k."""

from __future__ import annotations

import pytest
import torch

from mfg_lightning.models.mfg import MFG, keep_top_k


def test_paper_architecture_shapes() -> None:
    net = MFG(height=48, width=128).eval()
    out = net(torch.randn(2, 2, 48, 128))
    assert out.v_t.shape == out.v_omega.shape == (2, 2, 48, 128)
    assert out.hidden.shape == (2, 1000)
    assert (out.hidden >= 0).all()
    convs = [m for m in net.encoder if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [32, 32, 64, 64, 128, 256, 512, 1000]
    assert [c.kernel_size[0] for c in convs] == [5, 5, 5, 5, 5, 3, 3, 3]
    assert [c.stride[0] for c in convs] == [2, 1, 2, 1, 2, 2, 2, 1]
    # Bias-free linear decoders to half resolution.
    assert net.decoder_t.bias is None and net.decoder_omega.bias is None
    assert net.decoder_t.out_features == 2 * 24 * 64


def test_decoder_is_linear_in_the_hidden_units() -> None:
    net = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4))
    basis_t, basis_w = net.basis_fields()
    assert basis_t.shape == (10, 2, 16, 32)
    h = torch.rand(3, 10)
    v_t, v_w = net.decode(h)
    torch.testing.assert_close(v_t, torch.einsum("bm,mchw->bchw", h, basis_t), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_w, torch.einsum("bm,mchw->bchw", h, basis_w), atol=1e-5, rtol=1e-5)


def test_keep_top_k_keeps_the_most_active_units() -> None:
    h = torch.tensor([[0.1, 0.9, 0.5, 0.0, 0.7], [5.0, 4.0, 3.0, 2.0, 1.0]])
    kept = keep_top_k(h, 0.4)  # round(0.4 × 5) = 2 units per input
    expected = torch.tensor([[0.0, 0.9, 0.0, 0.0, 0.7], [5.0, 4.0, 0.0, 0.0, 0.0]])
    assert torch.equal(kept, expected)
    assert keep_top_k(h, 0.01).count_nonzero(dim=1).tolist() == [1, 1]  # at least one unit
    assert torch.equal(keep_top_k(h, None), h)


def test_top_k_applies_at_evaluation_only() -> None:
    torch.manual_seed(0)
    net = MFG(height=16, width=32, hidden_units=50, channels=(4, 4, 8, 8, 8), top_k=0.1)
    x = torch.randn(2, 2, 16, 32)
    net.eval()
    assert (net(x).hidden > 0).sum(dim=1).le(5).all()
    net.train()
    full = net(x).hidden
    assert torch.equal(full, net.encode(x)[0])
    net.eval()
    assert (net(x, top_k=1.0).hidden == full).all()


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, float("nan")])
def test_non_positive_or_too_large_top_k_is_refused(bad) -> None:
    with pytest.raises(ValueError, match="model.top_k"):
        MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4), top_k=bad)


def test_wrong_input_size_is_refused() -> None:
    net = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4))
    with pytest.raises(ValueError, match="built for 16×32"):
        net(torch.zeros(1, 2, 17, 32))
