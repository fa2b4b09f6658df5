"""The convolutions' three implementations (mfg_lightning.models.conv): the same numbers as
``nn.Conv2d`` forward and backward on every layer of the default encoder, interchangeable
checkpoints, and ``model.net.conv_impl=auto``'s measured, cached choice (the only tests that time
anything: the suite computes natively otherwise, tests/conftest.py)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from conftest import quiet_trainer
from mfg_lightning.core.machine import ISA_CAP_VARIABLES
from mfg_lightning.models.conv import (
    CONV_IMPLS,
    SwitchableConv2d,
    cache_path,
    choose_conv_impls,
    im2col_conv2d,
    machine_key,
    pick,
    switchable_layers,
)
from mfg_lightning.models.mfg import MFG
from mfg_lightning.run.convolutions import ConvolutionChoice, measured_dtype
from mfg_lightning.run.precision import cpu_has_native_bf16
from module_helpers import small_module

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


def test_pick_keeps_native_unless_another_is_clearly_faster() -> None:
    assert pick({"native": 10.0, "im2col": 9.8, "channels_last": 12.0}) == "native"
    assert pick({"native": 10.0, "im2col": 9.0, "channels_last": 12.0}) == "im2col"
    assert pick({"native": 10.0, "im2col": 13.0, "channels_last": 4.0}) == "channels_last"


def test_auto_measures_once_per_machine_then_reads_the_cache(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``auto`` times every layer (forward + backward, one warm-up + one repeat here), picks one
    implementation per layer, writes ``<cache_dir>/conv_impl/<machine>.json`` and logs each
    layer's times; a second network on the same machine reads the choice from the cache. The
    network's weights, its gradients and the global random state are untouched; a layer set to
    an implementation is left alone."""
    torch.manual_seed(0)
    net = MFG(**SMALL, conv_impl="auto")
    layers = dict(switchable_layers(net))
    layers["encoder.0"].impl = "channels_last"  # forced: not measured
    weights = {k: v.clone() for k, v in net.state_dict().items()}
    rng = torch.get_rng_state()
    with caplog.at_level(logging.INFO, logger="mfg_lightning.models.conv"):
        choices = choose_conv_impls(net, (2, 2, 16, 32), torch.float32, tmp_path, 1, 0.0)
    assert torch.equal(torch.get_rng_state(), rng)
    assert all(torch.equal(v, weights[k]) for k, v in net.state_dict().items())
    assert all(p.grad is None for p in net.parameters())
    assert [c.name for c in choices] == [n for n in layers if n != "encoder.0"]
    assert layers["encoder.0"].impl == "channels_last"
    for c in choices:
        assert not c.cached and set(c.ms) == set(CONV_IMPLS) and c.choice == pick(c.ms)
        assert layers[c.name].impl == c.choice
        assert all(ms > 0 for ms in c.ms.values())
        assert f"{c.name} (" in caplog.text
    assert "7 measured, 0 cached" in caplog.text
    (path,) = (tmp_path / "conv_impl").glob("*.json")
    stored = json.loads(path.read_text())
    assert stored["machine"]["threads"] == torch.get_num_threads()
    assert {"cpu", "features", "torch", "torch_cpu_capability"} <= set(stored["machine"])
    assert set(stored["layers"]) == {c.key for c in choices}
    key = "4->4 k5x5 s1x1 p2x2 d1x1 bias, input 2x4x8x16 float32 with its gradient, computed in "
    assert key + "float32" in stored["layers"]

    again = MFG(**SMALL, conv_impl="auto")
    dict(switchable_layers(again))["encoder.0"].impl = "channels_last"
    second = choose_conv_impls(again, (2, 2, 16, 32), torch.float32, tmp_path, 1, 0.0)
    assert all(c.cached for c in second)
    assert [(c.name, c.choice) for c in second] == [(c.name, c.choice) for c in choices]
    # Another batch size is another measurement.
    third = choose_conv_impls(MFG(**SMALL, conv_impl="auto"), (1, 2, 16, 32), cache_dir=tmp_path,
                              repeats=1, min_cpu_share=0.0)  # fmt: skip
    assert not any(c.cached for c in third)


def test_an_instruction_set_cap_is_another_machine(monkeypatch: pytest.MonkeyPatch) -> None:
    """oneDNN capped below the CPU (an AVX2 machine imitated on an AVX-512 one) runs other
    kernels: its times are cached under another key, and the cap is recorded in it."""
    for name in ISA_CAP_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    plain = machine_key(2)
    assert plain["isa_caps"] == {}
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    capped = machine_key(2)
    assert capped["isa_caps"] == {"ONEDNN_MAX_CPU_ISA": "AVX2"}
    assert cache_path("c", capped) != cache_path("c", plain)


def test_times_taken_on_a_busy_machine_are_neither_used_nor_cached(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Starved of the CPU while timing (here: a share no process reaches), the layers keep
    native, nothing is written and a warning says the next run times them again."""
    net = MFG(**SMALL, conv_impl="auto")
    with caplog.at_level(logging.WARNING, logger="mfg_lightning.models.conv"):
        choices = choose_conv_impls(net, (2, 2, 16, 32), cache_dir=tmp_path, repeats=1,
                                    min_cpu_share=10.0)  # fmt: skip
    assert len(choices) == 8 and all(c.choice == "native" for c in choices)
    assert {layer.impl for _, layer in switchable_layers(net)} == {"native"}
    assert not (tmp_path / "conv_impl").exists()
    assert "the machine was busy" in caplog.text and "times them again" in caplog.text


def test_the_training_hook_chooses_at_fit_setup_only(tmp_path: Path) -> None:
    """:class:`ConvolutionChoice` (added to every training run) chooses at the ``fit`` setup on
    a CPU, for float32 under ``32-true``; evaluation and a native network measure nothing."""
    module = small_module()
    for _, layer in switchable_layers(module.net):
        layer.impl = "auto"
    hook = ConvolutionChoice(batch_size=2, cache_dir=tmp_path, repeats=1, min_cpu_share=0.0)
    trainer = quiet_trainer(max_steps=1)
    hook.setup(trainer, module, "test")
    assert all(layer.impl == "auto" for _, layer in switchable_layers(module.net))
    hook.setup(trainer, module, "fit")
    assert all(layer.impl in CONV_IMPLS for _, layer in switchable_layers(module.net))
    (path,) = (tmp_path / "conv_impl").glob("*.json")
    keys = json.loads(path.read_text())["layers"]
    assert all(", input 2x" in k and k.endswith("computed in float32") for k in keys)

    native_cache = tmp_path / "native"
    ConvolutionChoice(2, native_cache).setup(trainer, small_module(), "fit")
    assert not native_cache.exists()


def test_a_run_records_its_choice_and_a_resumed_run_takes_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The choice goes into the run directory's record; a run that finds one (a resume) takes
    it without timing anything, even where timing would choose otherwise; a record of another
    network is said and ignored."""
    record = tmp_path / "conv_impl.json"
    trainer = quiet_trainer(max_steps=1)

    def auto_module():
        module = small_module()
        for _, layer in switchable_layers(module.net):
            layer.impl = "auto"
        return module

    first = auto_module()
    ConvolutionChoice(2, None, repeats=1, min_cpu_share=0.0, record=record).setup(
        trainer, first, "fit"
    )
    chosen = {name: layer.impl for name, layer in switchable_layers(first.net)}
    assert json.loads(record.read_text()) == {"layers": chosen}
    # Written by hand: im2col everywhere. A busy machine (a share no process reaches) would
    # give native to every layer it timed, so im2col can only come from the record.
    everywhere = {name: "im2col" for name in chosen}
    record.write_text(json.dumps({"layers": everywhere}))
    resumed = auto_module()
    busy = ConvolutionChoice(2, None, repeats=1, min_cpu_share=10.0, record=record)
    with caplog.at_level(logging.INFO, logger="mfg_lightning.run.convolutions"):
        busy.setup(trainer, resumed, "fit")
    assert {name: layer.impl for name, layer in switchable_layers(resumed.net)} == everywhere
    assert "the run's recorded choice" in caplog.text
    # Another network's record: said, then the layers are chosen (here: busy, so native).
    record.write_text(json.dumps({"layers": {"encoder.99": "im2col"}}))
    other = auto_module()
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        busy.setup(trainer, other, "fit")
    assert "records other layers" in caplog.text
    assert {layer.impl for _, layer in switchable_layers(other.net)} == {"native"}


def test_the_dtype_measured_follows_the_precision_and_the_cpu(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """float32 under 32-true; under a mixed precision bfloat16 where the CPU has it natively,
    else float32, said in the log."""
    assert measured_dtype("32-true") == torch.float32
    with caplog.at_level(logging.INFO, logger="mfg_lightning.run.convolutions"):
        dtype = measured_dtype("bf16-mixed")
    if cpu_has_native_bf16():
        assert dtype == torch.bfloat16
    else:
        assert dtype == torch.float32
        assert "lacks native bfloat16" in caplog.text and "float32 only" in caplog.text


def test_the_config_setting_reaches_every_layer() -> None:
    """``model.net.conv_impl`` sets every convolution; the suite's default is native
    (``$MFG_CONV_IMPL``, tests/conftest.py), so no test run times anything by itself."""
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    assert compose("train", []).model.net.conv_impl == "native"
    cfg = compose("train", ["model.net.conv_impl=im2col", "model.net.hidden_units=8"])
    net = instantiate(cfg.model.net)
    assert {layer.impl for _, layer in switchable_layers(net)} == {"im2col"}
    assert len(list(switchable_layers(net))) == 8
