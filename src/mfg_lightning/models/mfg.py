"""The Motion Field Generator network (paper section 4, Figure 2).

An asymmetric autoencoder: a fully convolutional encoder (conv + ReLU) ends in a global max-pool
to M non-negative hidden units; two bias-free linear decoders map the hidden units to the
translational (unit inverse depth) and rotational motion fields at half the input resolution,
upsampled bilinearly to the input resolution. Each decoder column is one unit's basis field.

Precision: under autocast (``trainer.precision=bf16-mixed`` / ``16-mixed``) the encoder runs in
the low precision; the decoders and the upsampling always run in float32, so the fields come out
in float32: recovering (t, ω) from exact 48 × 128 fields rounded to bfloat16 errs by up to
4.7e-4 m, against 3e-6 m from the float32 fields (the 64 motions of ``tests/test_precision.py``).

Convolutions: each is a :class:`mfg_lightning.models.conv.SwitchableConv2d` (``nn.Conv2d``'s
weights and state_dict; native, im2col or channels-last computation: ``model.net.conv_impl``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mfg_lightning.core.geometry import float32_math, to_float32
from mfg_lightning.models.conv import SwitchableConv2d, per_layer_impls


class MFGOutput(NamedTuple):
    """What :class:`MFG` returns.

    Attributes:
        v_t: ``(B, 2, H, W)`` translational field at unit inverse depth, pixels.
        v_omega: ``(B, 2, H, W)`` rotational field, pixels.
        hidden: ``(B, M)`` hidden activations after top-k (non-negative).
        hidden_map: ``(B, M, h, w)`` the last encoder feature map before the max-pool.
    """

    v_t: Tensor
    v_omega: Tensor
    hidden: Tensor
    hidden_map: Tensor


class StepFields(NamedTuple):
    """What a training or validation step hands to the figure callback
    (:class:`mfg_lightning.run.figures.TensorBoardFigures`) under its output's ``"fields"``
    key: the batch's fields as detached tensors on the model's device, ``(B, 2, H, W)`` pixels.

    Attributes:
        step: the global step the fields belong to.
        flow: the (masked) input flow.
        v_t, v_omega: the ground-truth translational (ρ = 1 m⁻¹) and rotational fields.
        v_t_pred, v_omega_pred: the predicted ones.
        hidden: ``(B, M)`` the hidden activations the prediction was decoded from.
    """

    step: int
    flow: Tensor
    v_t: Tensor
    v_omega: Tensor
    v_t_pred: Tensor
    v_omega_pred: Tensor
    hidden: Tensor

    @classmethod
    def of(cls, step: int, flow: Tensor, v_t: Tensor, v_w: Tensor, out: MFGOutput) -> StepFields:
        """A step's fields as detached views (no copy, no host read)."""
        return cls(step, flow.detach(), v_t.detach(), v_w.detach(),
                   out.v_t.detach(), out.v_omega.detach(), out.hidden.detach())  # fmt: skip


@runtime_checkable
class MotionFieldNetwork(Protocol):
    """What the training module, scoring, checkpoints and callbacks use of a network: a second
    encoder is one class with these members (and one ``conf/model`` file). :class:`MFG` is one.

    Attributes:
        height, width: the input flow's resolution, pixels.
        hidden_units: M, the number of hidden units.
    """

    height: int
    width: int
    hidden_units: int

    def encode(self, flow: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, 2, H, W)`` flow, pixels → hidden ``(B, M)`` (before top-k) and the hidden map
        ``(B, M, h, w)``."""
        ...

    def decode(self, hidden: Tensor) -> tuple[Tensor, Tensor]:
        """Hidden ``(B, M)`` → ``(v_t, v_ω)``, each ``(B, 2, H, W)`` pixels, float32."""
        ...

    def __call__(self, flow: Tensor) -> MFGOutput:
        """Encode and decode every unit: :func:`fields_at_each_k` at ``[ALL_UNITS]``."""
        ...


def fields_at_each_k(net: MotionFieldNetwork, flow: Tensor, ks: Sequence[float]) -> list[MFGOutput]:
    """The fields a network generates keeping the ``k`` fraction of its most active hidden units,
    for every ``k`` of ``ks``: one pass of the encoder, then :func:`keep_top_k` and the decoders
    for each ``k``. The one implementation of top-k, used by validation, test, ``evaluate`` and
    the study.

    Args:
        net: the network.
        flow: ``(B, 2, H, W)`` pixels.
        ks: fractions in (0, 1] (:func:`validate_top_k`); :data:`ALL_UNITS` keeps every unit.

    Returns:
        One :class:`MFGOutput` per ``k``, its ``hidden`` after top-k.
    """
    hidden, hidden_map = net.encode(flow)
    outputs = []
    for k in ks:
        kept = keep_top_k(hidden, k)
        v_t, v_omega = net.decode(kept)
        outputs.append(MFGOutput(v_t, v_omega, kept, hidden_map))
    return outputs


def input_size(net: MotionFieldNetwork) -> tuple[int, int]:
    """``(height, width)`` the network takes, pixels."""
    return net.height, net.width


#: The top-k fraction that keeps every hidden unit: the one way to say "all units".
ALL_UNITS = 1.0


def validate_top_k(top_k: float, key: str = "model.top_k") -> float:
    """Check a top-k fraction read from the config ``key``: a number in (0, 1], where
    :data:`ALL_UNITS` (1.0) keeps every unit."""
    if isinstance(top_k, bool) or not isinstance(top_k, (int, float)):
        raise ValueError(
            f"{key} must be a fraction in (0, 1] of hidden units (1.0: all), got {top_k!r}"
        )
    top_k = float(top_k)
    if not (0.0 < top_k <= 1.0) or math.isnan(top_k):
        raise ValueError(
            f"{key} must be a fraction in (0, 1] of hidden units (1.0: all), got {top_k}"
        )
    return top_k


def keep_top_k(hidden: Tensor, top_k: float) -> Tensor:
    """Keep the ``top_k`` fraction of most active units of each input, zero the rest.

    The paper's sparsity evaluation (section 5.3): ``k = max(1, round(top_k · M))`` units per
    input survive. Ties at the threshold are broken by ``torch.topk``'s order.

    Args:
        hidden: ``(B, M)`` activations.
        top_k: fraction in (0, 1]; :data:`ALL_UNITS` is the identity.
    """
    if top_k >= ALL_UNITS:
        return hidden
    k = max(1, round(top_k * hidden.shape[1]))
    idx = hidden.topk(k, dim=1).indices
    mask = torch.zeros_like(hidden).scatter_(1, idx, 1.0)
    return hidden * mask


def bilinear_matrix(
    n_in: int, n_out: int, align_corners: bool, device: torch.device | None = None
) -> Tensor:
    """The ``(n_out, n_in)`` float32 matrix of 1-D linear interpolation as ``F.interpolate``
    computes it (``mode="bilinear"`` is this along each axis; its default scale ``n_in / n_out``).

    Pixel ``i`` of the output samples the input at ``i · (n_in − 1) / (n_out − 1)``
    (``align_corners=True``) or ``(i + 0.5) · n_in / n_out − 0.5`` clamped at 0 (``False``).
    """
    # In float32, as PyTorch's own kernels compute the source positions and weights. The scale
    # is a Python number: a tensor-scalar product casts it to float32 inside the kernel, where
    # torch.tensor(scale, device=...) would be a synchronous host-to-device copy on a GPU.
    i = torch.arange(n_out, dtype=torch.float32, device=device)
    if align_corners:
        src = i * ((n_in - 1) / (n_out - 1) if n_out > 1 else 0.0)
    else:
        src = ((i + 0.5) * (n_in / n_out) - 0.5).clamp_min(0.0)
    lo = src.floor().long().clamp_max(n_in - 1)
    hi = (lo + 1).clamp_max(n_in - 1)
    frac = src - lo
    M = torch.zeros(n_out, n_in, device=device)
    rows = torch.arange(n_out, device=device)
    M.index_put_((rows, lo), 1 - frac, accumulate=True)
    M.index_put_((rows, hi), frac, accumulate=True)
    return M


def upsample_bilinear(field: Tensor, size: tuple[int, int], align_corners: bool) -> Tensor:
    """Bilinear upsampling of ``(B, C, h, w)`` to ``(B, C, *size)``.

    ``F.interpolate``, except on CUDA with deterministic algorithms on
    (``trainer.deterministic=true``): its backward there accumulates with atomic adds, has no
    deterministic kernel and raises. Bilinear upsampling is separable, ``M_h · f · M_wᵀ`` with the
    interpolation matrices of :func:`bilinear_matrix`, and two matrix products have a
    deterministic backward (cuBLAS with ``CUBLAS_WORKSPACE_CONFIG``, which Lightning sets). The
    two agree to float32 rounding (tests/test_precision.py); the CPU keeps ``F.interpolate``,
    whose backward is deterministic there.
    """
    if not (field.is_cuda and torch.are_deterministic_algorithms_enabled()):
        return F.interpolate(field, size=size, mode="bilinear", align_corners=align_corners)
    M_h = bilinear_matrix(field.shape[-2], size[0], align_corners, field.device).to(field)
    M_w = bilinear_matrix(field.shape[-1], size[1], align_corners, field.device).to(field)
    return M_h @ field @ M_w.T


#: ``model.net.init`` values (see :class:`MFG`).
INITS = ("torch", "xavier")


class MFG(nn.Module):
    """Motion Field Generator.

    Args:
        height, width: input flow resolution (pixels).
        hidden_units: M, the number of hidden units (paper: 1000).
        channels: output channels of the encoder blocks before the hidden layer.
        kernels: kernel size of every block, hidden block included (one more than channels).
        strides: stride of every block, hidden block included.
        double_blocks: how many leading blocks have two convolutions (the second has stride 1).
        decoder_scale: resolution of the decoded fields relative to the input (paper: 0.5).
        init: ``"torch"``: PyTorch's default initialisation of the convolutions; ``"xavier"``:
            ``xavier_uniform_`` weights and zero biases, as the authors' released code
            (hkashyap/SparseMotion) initialises every convolution.
        align_corners: of the bilinear upsampling of the decoded fields. ``True`` (the released
            code's) maps the corner pixels of the coarse and fine grids onto each other, so a
            field linear in the pixel coordinates (the translational field at unit depth) is
            represented exactly; ``False`` leaves a least-squares residual.
        input_scale: the input flow (pixels) is multiplied by this before the encoder. With the
            sparsity function's fixed B, the activations' scale sets the sparsity pressure; the
            released code feeds PWC-Net's raw output (about quarter-resolution pixels / 5).
        conv_impl: how the convolutions compute (:mod:`mfg_lightning.models.conv`, the same
            weights and state_dict whichever): ``native`` (PyTorch's ``nn.Conv2d``), ``im2col``
            (one gather and one GEMM), ``channels_last``, a list with one of these per
            convolution in module order (a training run's recorded choice), or ``auto``, which a
            training run resolves into that list before it builds the network
            (:mod:`mfg_lightning.run.machine_profile`); built elsewhere, ``auto`` runs ``native``.
    """

    def __init__(
        self,
        height: int = 48,
        width: int = 128,
        hidden_units: int = 1000,
        channels: Sequence[int] = (32, 64, 128, 256, 512),
        kernels: Sequence[int] = (5, 5, 5, 3, 3, 3),
        strides: Sequence[int] = (2, 2, 2, 2, 2, 1),
        double_blocks: int = 2,
        decoder_scale: float = 0.5,
        init: str = "xavier",
        align_corners: bool = True,
        input_scale: float = 1.0,
        conv_impl: str | Sequence[str] = "native",
    ) -> None:
        super().__init__()
        channels, kernels, strides = list(channels), list(kernels), list(strides)
        if not (len(kernels) == len(strides) == len(channels) + 1):
            raise ValueError(
                "model.net: kernels and strides need one entry per block including the hidden "
                f"block ({len(channels) + 1}), got {len(kernels)} and {len(strides)}"
            )
        if hidden_units <= 0:
            raise ValueError(f"model.net.hidden_units must be positive, got {hidden_units}")
        if init not in INITS:
            raise ValueError(f"model.net.init must be one of {INITS}, got {init!r}")
        if not (math.isfinite(input_scale) and input_scale > 0):
            raise ValueError(f"model.net.input_scale must be a positive number, got {input_scale}")
        blocks = len(channels) + 1
        convolutions = blocks + max(0, min(double_blocks, blocks))
        impls = iter(per_layer_impls(conv_impl, convolutions))
        self.height, self.width = height, width
        self.hidden_units = hidden_units
        self.align_corners = bool(align_corners)
        self.input_scale = float(input_scale)
        layers: list[nn.Module] = []
        c_in = 2
        for i, (c_out, k, s) in enumerate(
            zip([*channels, hidden_units], kernels, strides, strict=True)
        ):
            conv = SwitchableConv2d(c_in, c_out, k, stride=s, padding=k // 2, impl=next(impls))
            layers += [conv, nn.ReLU(inplace=True)]
            if i < double_blocks:
                conv = SwitchableConv2d(c_out, c_out, k, stride=1, padding=k // 2, impl=next(impls))
                layers += [conv, nn.ReLU(inplace=True)]
            c_in = c_out
        self.encoder = nn.Sequential(*layers)
        self.out_height = max(1, round(height * decoder_scale))
        self.out_width = max(1, round(width * decoder_scale))
        n_out = 2 * self.out_height * self.out_width
        self.decoder_t = nn.Linear(hidden_units, n_out, bias=False)
        self.decoder_omega = nn.Linear(hidden_units, n_out, bias=False)
        if init == "xavier":
            for module in self.encoder:
                if isinstance(module, nn.Conv2d):
                    nn.init.xavier_uniform_(module.weight)
                    nn.init.zeros_(module.bias)

    def encode(self, flow: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, 2, H, W)`` flow → hidden ``(B, M)`` (before top-k) and the map ``(B, M, h, w)``."""
        if flow.shape[-2:] != (self.height, self.width):
            raise ValueError(
                f"MFG was built for {self.height}×{self.width} flow, got {tuple(flow.shape[-2:])}"
            )
        hidden_map = self.encoder(flow * self.input_scale if self.input_scale != 1.0 else flow)
        return hidden_map.amax(dim=(2, 3)), hidden_map

    def decode(self, hidden: Tensor) -> tuple[Tensor, Tensor]:
        """Hidden ``(B, M)`` → ``(v_t, v_ω)``, each ``(B, 2, H, W)`` pixels, in float32 (float64
        hidden units: float64) whatever the autocast around the call."""
        fields = []
        size = (self.height, self.width)
        with float32_math():
            hidden = to_float32(hidden)
            for decoder in (self.decoder_t, self.decoder_omega):
                f = decoder(hidden).view(-1, 2, self.out_height, self.out_width)
                if (self.out_height, self.out_width) != size:
                    f = upsample_bilinear(f, size, self.align_corners)
                fields.append(f)
        return fields[0], fields[1]

    def basis_fields(self) -> tuple[Tensor, Tensor]:
        """Every unit's decoder columns as fields: ``(M, 2, H, W)`` translational and rotational."""
        eye = torch.eye(self.hidden_units, device=self.decoder_t.weight.device)
        return self.decode(eye)

    def forward(self, flow: Tensor) -> MFGOutput:
        """Flow ``(B, 2, H, W)`` in pixels → :class:`MFGOutput` of every unit (top-k is an
        evaluation setting: :func:`fields_at_each_k`)."""
        return fields_at_each_k(self, flow, [ALL_UNITS])[0]
