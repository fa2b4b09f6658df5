"""The convolutions' three implementations (mfg_lightning.models.conv): the same numbers as
``nn.Conv2d`` forward and backward on every layer of the default encoder, interchangeable
checkpoints, and the setting, one for every layer or a list per layer (``auto``'s measurement:
tests/test_machine_profile.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from mfg_lightning.models.conv import CONV_IMPLS, SwitchableConv2d, im2col_conv2d, switchable_layers
from mfg_lightning.models.mfg import MFG

OTHER_IMPLS = [i for i in CONV_IMPLS if i != "native"]
#: A small network of the default's architecture (kernels 5 and 3, strides 2 and 1).
NAMES = ("output", "input grad", "weight grad", "bias grad")
SMALL = dict(height=16, width=32, hidden_units=8, channels=(4, 4, 4, 4, 4))


def default_layer_inputs(batch: int = 2) -> list[tuple[SwitchableConv2d, tuple[int, ...]]]:
    """Every convolution of the default MFG (48 × 128, M = 1000) with the input shape it gets."""
    net = MFG()
    shapes: dict[str, tuple[int, ...]] = {}

    def record(name: str, args: tuple[Tensor, ...]) -> None:
        shapes.setdefault(name, tuple(args[0].shape))

    hooks = [
        layer.register_forward_pre_hook(lambda m, a, n=name: record(n, a))
        for name, layer in switchable_layers(net)
    ]
    with torch.no_grad():
        net.encode(torch.zeros(batch, 2, net.height, net.width))
    for hook in hooks:
        hook.remove()
    return [(layer, tuple(shapes[name])) for name, layer in switchable_layers(net)]


def twin(reference: nn.Conv2d, impl: str) -> SwitchableConv2d:
    """A :class:`SwitchableConv2d` of ``reference``'s geometry and weights running ``impl``."""
    layer = SwitchableConv2d(
        reference.in_channels, reference.out_channels, reference.kernel_size,
        stride=reference.stride, padding=reference.padding, impl=impl,
    )  # fmt: skip
    layer.load_state_dict(reference.state_dict())
    return layer.to(reference.weight.dtype)


def forward_backward(layer: nn.Module, x: Tensor, grad: Tensor) -> tuple[Tensor, ...]:
    """Output, input gradient, weight gradient and bias gradient of one forward + backward."""
    x = x.detach().clone().requires_grad_(True)
    y = layer(x)
    y.backward(grad)
    return y.detach(), x.grad, layer.weight.grad, layer.bias.grad


def test_the_default_encoder_has_every_geometry() -> None:
    """Kernels 5 and 3, strides 2 and 1, padding k // 2: what the equality tests below cover."""
    geometries = {(l.kernel_size[0], l.stride[0], l.padding[0]) for l, _ in default_layer_inputs()}
    assert geometries == {(5, 2, 2), (5, 1, 2), (3, 2, 1), (3, 1, 1)}


@pytest.mark.parametrize("impl", OTHER_IMPLS)
@pytest.mark.parametrize(
    ("dtype", "tol"), [(torch.float64, 1e-11), (torch.float32, 2e-5)], ids=["float64", "float32"]
)
def test_every_default_layer_equals_nn_conv2d_forward_and_backward(
    impl: str, dtype: torch.dtype, tol: float
) -> None:
    """Output, input gradient, weight and bias gradients of each of the default encoder's 8
    convolutions (2 → 32 … 512 → 1000 on its 2 × 4 map) equal ``nn.Conv2d``'s on the same
    weights, within rounding (tolerance relative to the values' scale)."""
    gen = torch.Generator().manual_seed(1)
    for layer, shape in default_layer_inputs():
        reference = nn.Conv2d(
            layer.in_channels, layer.out_channels, layer.kernel_size,
            stride=layer.stride, padding=layer.padding,
        ).to(dtype)  # fmt: skip
        reference.load_state_dict(layer.state_dict())
        x = torch.randn(shape, generator=gen, dtype=dtype)
        y = reference(x)
        grad = torch.randn(y.shape, generator=gen, dtype=dtype)
        expected = forward_backward(reference, x, grad)
        got = forward_backward(twin(reference, impl), x, grad)
        for name, a, b in zip(NAMES, got, expected, strict=True):
            assert a.shape == b.shape and a.dtype == b.dtype, name
            torch.testing.assert_close(
                a, b, rtol=tol, atol=tol * float(b.abs().max()), msg=f"{layer}: {name}"
            )


@pytest.mark.parametrize("impl", OTHER_IMPLS)
def test_under_bf16_autocast_as_nn_conv2d_within_bf16_rounding(impl: str) -> None:
    """Under CPU bf16 autocast (``bf16-mixed``) each implementation computes in bfloat16 too and
    agrees with ``nn.Conv2d`` to bfloat16's rounding (8 bits of mantissa), forward and backward:
    the first layer (float32 flow in) and a deep 3 × 3 one."""
    gen = torch.Generator().manual_seed(2)
    layers = default_layer_inputs()
    for layer, shape in (layers[0], layers[-2]):
        reference = twin(layer, "native")
        x = torch.randn(shape, generator=gen)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            y = reference(x)
        grad = torch.randn(y.shape, generator=gen).to(y.dtype)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            expected = forward_backward(reference, x, grad)
            got = forward_backward(twin(layer, impl), x, grad)
        assert got[0].dtype == expected[0].dtype == torch.bfloat16
        for a, b in zip(got, expected, strict=True):
            scale = float(b.float().abs().max())
            torch.testing.assert_close(a.float(), b.float(), rtol=2e-2, atol=2e-2 * scale)


def test_a_network_mixing_the_implementations_equals_the_native_one() -> None:
    """Layers of different implementations in a row (each converts the memory format it gets)
    give the native network's fields, hidden units and every parameter's gradient."""
    torch.manual_seed(0)
    native = MFG(**SMALL).double()
    mixed = MFG(**SMALL).double()
    mixed.load_state_dict(native.state_dict())
    for i, (_, layer) in enumerate(switchable_layers(mixed)):
        layer.impl = CONV_IMPLS[(i + 1) % len(CONV_IMPLS)]
    flow = torch.randn(3, 2, 16, 32, dtype=torch.float64)
    outs = []
    for net in (native, mixed):
        out = net(flow)
        (out.v_t.square().sum() + out.v_omega.abs().sum() + out.hidden.sum()).backward()
        outs.append(out)
    torch.testing.assert_close(outs[1].v_t, outs[0].v_t)
    torch.testing.assert_close(outs[1].hidden, outs[0].hidden)
    for (name, a), (_, b) in zip(native.named_parameters(), mixed.named_parameters(), strict=True):
        torch.testing.assert_close(b.grad, a.grad, msg=name)


@pytest.mark.parametrize(("saved", "loaded"), [("im2col", "channels_last"), ("native", "im2col"),
                                               ("channels_last", "native")])  # fmt: skip
def test_a_checkpoint_saved_under_one_implementation_loads_under_another(
    tmp_path: Path, saved: str, loaded: str
) -> None:
    """The state_dict's keys and shapes are nn.Conv2d's whatever runs: weights saved under one
    implementation load strictly under another and give the same output."""
    torch.manual_seed(0)
    source = MFG(**SMALL, conv_impl=saved)
    torch.save(source.state_dict(), tmp_path / "weights.pt")
    target = MFG(**SMALL, conv_impl=loaded)
    state = torch.load(tmp_path / "weights.pt", weights_only=True)
    assert {k: v.shape for k, v in state.items()} == {
        k: v.shape for k, v in target.state_dict().items()
    }
    target.load_state_dict(state, strict=True)
    flow = torch.randn(2, 2, 16, 32)
    torch.testing.assert_close(target(flow).v_t, source(flow).v_t, rtol=1e-5, atol=1e-6)
    assert all(layer.impl == loaded for _, layer in switchable_layers(target))


def test_the_setting_is_checked() -> None:
    with pytest.raises(ValueError, match="model.net.conv_impl must be one of"):
        MFG(**SMALL, conv_impl="fastest")
    grouped = SwitchableConv2d(4, 4, 3, padding=1, groups=2)
    assert grouped.candidates() == ("native", "channels_last")
    with pytest.raises(ValueError, match="im2col supports groups=1"):
        grouped.impl = "im2col"
    assert "impl=native" in repr(grouped)


def test_im2col_handles_dilation() -> None:
    """The lowering is a general 2-D convolution (dilation included), not only the encoder's."""
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(2, 3, 11, 13, generator=gen, dtype=torch.float64)
    w = torch.randn(5, 3, 3, 2, generator=gen, dtype=torch.float64)
    b = torch.randn(5, generator=gen, dtype=torch.float64)
    expected = torch.nn.functional.conv2d(x, w, b, (2, 1), (2, 1), (2, 3))
    torch.testing.assert_close(im2col_conv2d(x, w, b, (2, 1), (2, 1), (2, 3)), expected)


def test_the_config_setting_reaches_every_layer() -> None:
    """``model.net.conv_impl`` sets every convolution, or each with a list in module order (a
    run's recorded choice); a list of another length names the key and both counts. The
    default is ``auto``, which a training run resolves (tests/test_machine_profile.py)."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    assert compose("train", []).model.net.conv_impl == "auto"
    cfg = compose("train", ["model.net.conv_impl=im2col", "model.net.hidden_units=8"])
    net = instantiate(cfg.model.net)
    assert {layer.impl for _, layer in switchable_layers(net)} == {"im2col"}
    assert len(list(switchable_layers(net))) == 8
    mixed = ["native", "im2col", "channels_last", "native", "im2col", "native", "native", "im2col"]
    cfg = compose("train", [f"model.net.conv_impl=[{','.join(mixed)}]"])
    assert [layer.impl for _, layer in switchable_layers(instantiate(cfg.model.net))] == mixed
    with pytest.raises(ValueError, match="lists 3 implementations, but the network has 8"):
        MFG(**SMALL, conv_impl=["native"] * 3)
    with pytest.raises(ValueError, match="model.net.conv_impl must be one of"):
        MFG(**SMALL, conv_impl=["native"] * 7 + ["winograd"])
