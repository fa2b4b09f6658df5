"""The MFG network: shapes, non-negativity, top-k."""

from __future__ import annotations

import math

import pytest
import torch

from mfg_lightning.models.mfg import ALL_UNITS, MFG, fields_at_each_k, keep_top_k, validate_top_k


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
    assert torch.equal(keep_top_k(h, ALL_UNITS), h)


def test_every_k_from_one_pass_of_the_encoder() -> None:
    """The network's forward keeps every unit; ``fields_at_each_k`` keeps each k's most active
    units after one encoder pass, each k's fields those of that k alone."""
    torch.manual_seed(0)
    net = MFG(height=16, width=32, hidden_units=50, channels=(4, 4, 8, 8, 8)).eval()
    x = torch.randn(2, 2, 16, 32)
    full = net(x).hidden
    assert torch.equal(full, net.encode(x)[0])
    sparse, every = fields_at_each_k(net, x, [0.1, ALL_UNITS])
    assert (sparse.hidden > 0).sum(dim=1).le(5).all()
    assert torch.equal(every.hidden, full)
    (alone,) = fields_at_each_k(net, x, [0.1])
    assert torch.equal(alone.v_t, sparse.v_t) and torch.equal(alone.v_omega, sparse.v_omega)


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, float("nan"), None, "all"])
def test_non_positive_or_too_large_top_k_is_refused(bad) -> None:
    with pytest.raises(ValueError, match="model.top_k"):
        validate_top_k(bad)


def test_wrong_input_size_is_refused() -> None:
    net = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4))
    with pytest.raises(ValueError, match="built for 16×32"):
        net(torch.zeros(1, 2, 17, 32))


def _upsampling_residual(align_corners: bool) -> float:
    """Largest |error| (px) of the best decoder column for the translational field at unit
    depth of a forward motion, at 24 × 64 with KITTI intrinsics, decoded at half resolution."""
    from mfg_lightning.core import geometry
    from mfg_lightning.scene.camera import kitti_like_intrinsics

    H, W = 24, 64
    n = (H // 2) * (W // 2)
    net = MFG(height=H, width=W, hidden_units=n, channels=(2, 2, 2, 2, 2),
              align_corners=align_corners)  # fmt: skip
    K = kitti_like_intrinsics(H, W).float()[None]
    v_t = geometry.translational_field(torch.tensor([[0.1, -0.05, 1.0]]), K, H, W)
    with torch.no_grad():
        # Unit i writes coarse pixel i of the u channel: decoding them all gives the decoder's
        # linear map from a coarse field to the output field.
        net.decoder_t.weight.zero_()
        net.decoder_t.weight[:n] = torch.eye(n)
        U = net.decode(torch.eye(n))[0][:, 0].reshape(n, H * W).T.double()  # (H·W, h·w)
        residual = 0.0
        for c in range(2):
            target = v_t[0, c].flatten().double()[:, None]
            coarse = torch.linalg.lstsq(U, target).solution
            residual = max(residual, float((U @ coarse - target).abs().max()))
    return residual


def test_align_corners_represents_the_translational_field_exactly() -> None:
    assert _upsampling_residual(align_corners=True) < 1e-4  # float32 rounding of ~100 px
    assert _upsampling_residual(align_corners=False) > 0.05


def test_xavier_initialisation_as_the_released_code() -> None:
    torch.manual_seed(0)
    net = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4), init="xavier")
    convs = [m for m in net.encoder if isinstance(m, torch.nn.Conv2d)]
    assert convs
    for conv in convs:
        fan_in = conv.in_channels * conv.kernel_size[0] * conv.kernel_size[1]
        fan_out = conv.out_channels * conv.kernel_size[0] * conv.kernel_size[1]
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        assert (conv.bias == 0).all()
        assert conv.weight.abs().max() <= bound
        assert conv.weight.abs().max() > 0.8 * bound  # uniform over the whole range
    # The default is the released code's; "torch" keeps PyTorch's (non-zero biases).
    torch.manual_seed(0)
    default = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4))
    pairs = zip(default.state_dict().values(), net.state_dict().values(), strict=True)
    assert all(torch.equal(a, b) for a, b in pairs)
    torch.manual_seed(0)
    plain = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4), init="torch")
    assert any((m.bias != 0).any() for m in plain.encoder if isinstance(m, torch.nn.Conv2d))
    with pytest.raises(ValueError, match="model.net.init"):
        MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4), init="he")


def test_input_scale_multiplies_the_flow_before_the_encoder() -> None:
    torch.manual_seed(0)
    scaled = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4), input_scale=0.2)
    plain = MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4))
    plain.load_state_dict(scaled.state_dict())
    flow = torch.randn(3, 2, 16, 32)
    torch.testing.assert_close(scaled(flow).hidden, plain(0.2 * flow).hidden)
    with pytest.raises(ValueError, match="model.net.input_scale"):
        MFG(height=16, width=32, hidden_units=10, channels=(4, 4, 4, 4, 4), input_scale=0.0)


def test_config_defaults_are_the_released_codes_and_match_the_code() -> None:
    """One default per setting: conf/model/mfg.yaml and the constructors agree, and both follow
    the authors' released code where the paper is silent or ambiguous (docs/configuration.md)."""
    import inspect

    from mfg_lightning.core.config import compose
    from mfg_lightning.models.losses import MFGLoss

    cfg = compose("train", [])
    net = inspect.signature(MFG).parameters
    loss = inspect.signature(MFGLoss).parameters
    assert cfg.model.net.init == net["init"].default == "xavier"
    assert cfg.model.net.align_corners is net["align_corners"].default is True
    assert cfg.model.net.input_scale == net["input_scale"].default == 1.0
    assert cfg.model.loss.balance_squared is loss["balance_squared"].default is False
