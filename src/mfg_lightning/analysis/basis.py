"""The egomotion basis of a trained MFG and its population sparsity.

Each hidden unit ``j`` of MFG owns one column of each linear decoder: decoding the one-hot
activation ``e_j`` gives its translational basis field (at unit inverse depth, ρ = 1 m⁻¹) and its
rotational basis field, ``(2, H, W)`` pixels per frame at the input resolution. The unit's
*preferred* translation ``t_j`` (m per frame) and rotation ``ω_j`` (rad per frame) are the
closed-form egomotion of those fields, :func:`mfg_lightning.core.geometry.recover_motion` with the
test inputs' intrinsics (``docs/protocols.md``, "Basis selectivity"): the motion the
unit stands for at activation 1. They follow this project's convention, the camera's own motion
(driving forward: ``t_z > 0``); the paper prints the opposite sign (the scene's motion relative to
the camera). Units are ordered by the L2 norm of their decoder weights, both decoders' columns
together (supplementary §2.4).

The figures and files of ``python -m mfg_lightning.analyze_basis`` are
:mod:`mfg_lightning.analysis.basis_report`'s.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.data.sample import model_inputs

if TYPE_CHECKING:
    from mfg_lightning.models.mfg import MFG

log = logging.getLogger("mfg_lightning.analysis.basis")

SELECTIVITY_COLUMNS = ("unit", "norm", "tx", "ty", "tz", "wx", "wy", "wz")


# --------------------------------------------------------------------------------------------
# The basis and its selectivity
# --------------------------------------------------------------------------------------------


def decoder_norms(net: MFG) -> Tensor:
    """L2 norm of every unit's decoder weights, both decoders' columns together. ``(M,)``."""
    w_t = net.decoder_t.weight.detach()
    w_omega = net.decoder_omega.weight.detach()
    return (w_t.square().sum(0) + w_omega.square().sum(0)).sqrt().cpu()


@torch.no_grad()
def unit_fields(net: MFG, units: Sequence[int] | Tensor, chunk: int = 256) -> tuple[Tensor, Tensor]:
    """The basis fields of some units: their decoder columns decoded at the input resolution.

    Equivalent to rows of :meth:`MFG.basis_fields`, in chunks, so a large M at a large
    resolution does not decode every unit at once.

    Args:
        units: unit indices, ``(U,)``.

    Returns:
        ``(v_t, v_ω)``, each ``(U, 2, H, W)`` pixels: the translational field at unit inverse
        depth and the rotational field of activation 1.
    """
    units = torch.as_tensor(units, dtype=torch.long)
    device = net.decoder_t.weight.device
    parts_t, parts_w = [], []
    for start in range(0, len(units), chunk):
        idx = units[start : start + chunk].to(device)
        one_hot = torch.zeros(len(idx), net.hidden_units, device=device)
        one_hot[torch.arange(len(idx), device=device), idx] = 1.0
        v_t, v_w = net.decode(one_hot)
        parts_t.append(v_t.cpu())
        parts_w.append(v_w.cpu())
    if not parts_t:
        empty = torch.zeros(0, 2, net.height, net.width)
        return empty, empty.clone()
    return torch.cat(parts_t), torch.cat(parts_w)


def preferred_motions(
    net: MFG, intrinsics: Tensor, units: Sequence[int] | Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Each unit's preferred translation and rotation (closed-form recovery from its fields).

    Args:
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)`` in pixels at the model's input resolution.
        units: unit indices (None: all ``M``).

    Returns:
        ``(t, ω)``, each ``(U, 3)`` float64: metres and radians per frame for activation 1,
        in the camera's own-motion convention of :mod:`mfg_lightning.core.geometry`.
    """
    units = torch.arange(net.hidden_units) if units is None else torch.as_tensor(units)
    v_t, v_w = unit_fields(net, units)
    t, w = geometry.recover_motion(v_t.double(), v_w.double(), intrinsics.double().cpu())
    return t, w


def selectivity_rows(net: MFG, intrinsics: Tensor, n_units: int) -> list[dict[str, float]]:
    """The ``n_units`` units of largest decoder norm, in decreasing order, with their preferred
    motion: dicts with :data:`SELECTIVITY_COLUMNS` (supplementary Figures 6 and 8)."""
    norms = decoder_norms(net)
    order = torch.argsort(norms, descending=True, stable=True)[: max(0, n_units)]
    t, w = preferred_motions(net, intrinsics, order)
    return [
        {
            "unit": int(u),
            "norm": float(norms[u]),
            **{k: float(v) for k, v in zip(("tx", "ty", "tz"), t[i].tolist(), strict=True)},
            **{k: float(v) for k, v in zip(("wx", "wy", "wz"), w[i].tolist(), strict=True)},
        }
        for i, u in enumerate(order.tolist())
    ]


def decoder_column_norms(net: MFG) -> tuple[Tensor, Tensor]:
    """L2 norm of every unit's column in each decoder separately: ``(M,)`` translational,
    ``(M,)`` rotational (the supplement ranks each decoder's units by its own norm)."""
    w_t = net.decoder_t.weight.detach().double()
    w_omega = net.decoder_omega.weight.detach().double()
    return w_t.square().sum(0).sqrt().cpu(), w_omega.square().sum(0).sqrt().cpu()


def decoder_selectivity(
    net: MFG, intrinsics: Tensor, stats: PopulationStats, n_units: int
) -> dict[str, dict[str, Any]]:
    """Claim 5 as the supplement measures it, per decoder, in scale-free terms.

    For each decoder (``"t"``: translational, ``"omega"``: rotational) the ``n_units`` units of
    largest column norm *in that decoder* (Figures 5–8 rank each set by its own decoder), and for
    each unit: the closed-form motion of its field at activation 1 (``|t|`` m or ``|ω|`` rad per
    frame), its typical non-zero activation on ``stats``' inputs (mean activation when active),
    the motion at that activation (ReLU is positively homogeneous: an activation scale and a
    decoder column trade freely, their product does not), and the relative residual of the
    one-motion fit of its field.

    Returns:
        ``{"t": {...}, "omega": {...}}``, each with ``units``, ``column_norm``, ``motion_at_1``,
        ``typical_activation``, ``motion_typical``, ``residual``, ``firing_rate`` (lists in rank
        order), ``directions`` ``(U, 3)`` (unit vectors, as lists) and their ``resultant``
        length (1: one direction; 0: spread evenly).
    """
    n_t, n_w = decoder_column_norms(net)
    fired = stats.firing_counts.double()
    typical = torch.where(fired > 0, stats.activation_sums / fired.clamp_min(1), 0.0)
    rates = stats.firing_rates.double()
    K = intrinsics.double().cpu()
    out: dict[str, dict[str, Any]] = {}
    for key, norms in (("t", n_t), ("omega", n_w)):
        order = torch.argsort(norms, descending=True, stable=True)[: max(0, n_units)]
        v_t, v_w = unit_fields(net, order)
        v_t, v_w = v_t.double(), v_w.double()
        t, w = geometry.recover_motion(v_t, v_w, K)
        if key == "t":
            motion, field = t, v_t
            fit = geometry.translational_field(t, K, net.height, net.width)
        else:
            motion, field = w, v_w
            fit = geometry.rotational_field(w, K, net.height, net.width)
        residual = (field - fit).flatten(1).norm(dim=1) / field.flatten(1).norm(dim=1).clamp_min(
            1e-12
        )
        size = motion.norm(dim=1)
        direction = motion / size[:, None].clamp_min(1e-12)
        a = typical[order]
        out[key] = {
            "units": order.tolist(),
            "column_norm": norms[order].tolist(),
            "motion_at_1": size.tolist(),
            "typical_activation": a.tolist(),
            "motion_typical": (size * a).tolist(),
            "residual": residual.tolist(),
            "firing_rate": rates[order].tolist(),
            "directions": direction.tolist(),
            "resultant": float(direction.mean(0).norm()) if len(order) else math.nan,
        }
    return out


# --------------------------------------------------------------------------------------------
# Population sparsity
# --------------------------------------------------------------------------------------------


@dataclass
class PopulationStats:
    """Hidden activations over a set of inputs, before top-k (active: activation > 0).

    Attributes:
        active_per_input: ``(N,)`` number of active units of each input.
        sample_ids: the inputs' ``sample_id``, ``N`` strings.
        firing_counts: ``(M,)`` on how many inputs each unit was active.
        activation_sums: ``(M,)`` sum of each unit's activation over the inputs.
    """

    active_per_input: Tensor
    sample_ids: list[str]
    firing_counts: Tensor
    activation_sums: Tensor

    @property
    def n_inputs(self) -> int:
        return int(self.active_per_input.numel())

    @property
    def hidden_units(self) -> int:
        return int(self.firing_counts.numel())

    @property
    def firing_rates(self) -> Tensor:
        """``(M,)`` fraction of inputs on which each unit fired."""
        return self.firing_counts.double() / max(self.n_inputs, 1)

    @property
    def mean_activations(self) -> Tensor:
        """``(M,)`` mean activation of each unit over all inputs (zeros included)."""
        return self.activation_sums / max(self.n_inputs, 1)

    def summary(self) -> dict[str, Any]:
        a = self.active_per_input.double()
        n = self.n_inputs
        rates = self.firing_rates
        return {
            "n_inputs": n,
            "hidden_units": self.hidden_units,
            "active_units_mean": float(a.mean()) if n else None,
            "active_units_median": float(a.median()) if n else None,
            "active_units_min": int(a.min()) if n else None,
            "active_units_max": int(a.max()) if n else None,
            "active_fraction_mean": float(a.mean() / self.hidden_units) if n else None,
            "units_never_active": int((self.firing_counts == 0).sum()),
            "units_always_active": int((self.firing_counts == n).sum()) if n else 0,
            "firing_rate_median": float(rates.median()) if n else None,
        }


@torch.no_grad()
def population_statistics(
    net: MFG, loader: Any, max_batches: int | None = None, device: str | torch.device = "cpu"
) -> PopulationStats:
    """Encode every batch of ``loader`` and count active units per input and per unit.

    Uses :meth:`MFG.encode` (activations before top-k): the sparsity the training produced,
    not the one imposed at evaluation. Non-finite flow pixels are zeroed as in training.
    """
    net = net.eval().to(device)
    counts: list[Tensor] = []
    ids: list[str] = []
    firing = torch.zeros(net.hidden_units, dtype=torch.long)
    sums = torch.zeros(net.hidden_units, dtype=torch.float64)
    for i, batch in enumerate(loader):
        if max_batches is not None and i >= max_batches:
            break
        if batch is None:  # every sample of the batch was unreadable and skipped
            continue
        flow = model_inputs(batch).flow
        hidden, _ = net.encode(flow.to(device))
        active = (hidden > 0).cpu()
        counts.append(active.sum(1))
        firing += active.sum(0)
        sums += hidden.double().sum(0).cpu()
        ids += [str(s) for s in batch.get("sample_id", [""] * len(flow))]
    per_input = torch.cat(counts) if counts else torch.zeros(0, dtype=torch.long)
    return PopulationStats(per_input, ids, firing, sums)
