"""Pixel grids, the A(p) and B(p) matrices, the motion fields, their closed-form inversion, and
the exact reprojection flow they approximate (conventions: :mod:`mfg_lightning.core.geometry`)."""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import Tensor

from mfg_lightning.core.geometry.precision import full_precision

_EPS = 1e-8


# --------------------------------------------------------------------------------------------
# Pixel grids and the A, B matrices
# --------------------------------------------------------------------------------------------


def _as_batch_intrinsics(intrinsics: Tensor) -> Tensor:
    """Return intrinsics shaped ``(B, 4)`` (a single ``(4,)`` row is given a batch of 1)."""
    if intrinsics.dim() == 1:
        intrinsics = intrinsics.unsqueeze(0)
    if intrinsics.dim() != 2 or intrinsics.shape[-1] != 4:
        raise ValueError(
            f"intrinsics must be (B, 4) = (fx, fy, cx, cy), got shape {tuple(intrinsics.shape)}"
        )
    return intrinsics


@full_precision
def normalized_grid(intrinsics: Tensor, height: int, width: int) -> Tensor:
    """Normalised image coordinates of every pixel centre.

    Args:
        intrinsics: ``(B, 4)`` ``(fx, fy, cx, cy)`` in pixels at this resolution.
        height, width: grid size in pixels.

    Returns:
        ``(B, 2, H, W)``: ``x = (u - cx) / fx`` and ``y = (v - cy) / fy`` (dimensionless).
    """
    K = _as_batch_intrinsics(intrinsics)
    u = torch.arange(width, device=K.device, dtype=K.dtype)
    v = torch.arange(height, device=K.device, dtype=K.dtype)
    fx, fy, cx, cy = (K[:, i, None, None] for i in range(4))
    x = (u[None, None, :] - cx) / fx
    y = (v[None, :, None] - cy) / fy
    return torch.stack(torch.broadcast_tensors(x, y), dim=1)


@full_precision
def motion_matrices(intrinsics: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """The A(p) and B(p) matrices of every pixel, in pixel units.

    Args:
        intrinsics: ``(B, 4)`` ``(fx, fy, cx, cy)`` in pixels.
        height, width: grid size.

    Returns:
        ``(A, B)``, each ``(B, H, W, 2, 3)``: ``A @ t`` is the translational image velocity in
        pixels at inverse depth 1 m⁻¹ for a camera translation ``t`` (m); ``B @ ω`` the rotational
        one for a rotation vector ``ω`` (rad). See the module docstring for the sign convention.
    """
    K = _as_batch_intrinsics(intrinsics)
    n = K.shape[0]
    # The columns of A and B are the fields of the unit motions: one writing of the formulas
    # (the field functions below, the hot path of the losses), not three.
    units = torch.eye(3, dtype=K.dtype, device=K.device).repeat(n, 1)  # (3n, 3)
    K3 = K.repeat_interleave(3, dim=0)

    def columns(field: Tensor) -> Tensor:  # (3n, 2, H, W) → (n, H, W, 2, 3)
        return field.view(n, 3, 2, height, width).permute(0, 3, 4, 2, 1)

    A = columns(translational_field(units, K3, height, width))
    B = columns(rotational_field(units, K3, height, width))
    return A, B


@full_precision
def translational_field(t: Tensor, intrinsics: Tensor, height: int, width: int) -> Tensor:
    """Translational motion field at unit inverse depth, ``v_t = A t``.

    Args:
        t: ``(B, 3)`` camera translation in metres per frame (camera-k coordinates).
        intrinsics: ``(B, 4)`` or ``(4,)`` in pixels.

    Returns:
        ``(B, 2, H, W)`` pixels per frame for a scene at depth 1 m (ρ = 1 m⁻¹).
    """
    K = _as_batch_intrinsics(intrinsics).to(t)
    xy = normalized_grid(K, height, width)
    x, y = xy[:, 0], xy[:, 1]
    tx, ty, tz = (t[:, i, None, None] for i in range(3))
    u = K[:, 0, None, None] * (-tx + x * tz)
    v = K[:, 1, None, None] * (-ty + y * tz)
    return torch.stack([u, v], dim=1)


@full_precision
def rotational_field(omega: Tensor, intrinsics: Tensor, height: int, width: int) -> Tensor:
    """Rotational motion field ``v_ω = B ω`` (independent of depth).

    Args:
        omega: ``(B, 3)`` camera rotation vector in radians per frame.
        intrinsics: ``(B, 4)`` or ``(4,)`` in pixels.

    Returns:
        ``(B, 2, H, W)`` pixels per frame.
    """
    K = _as_batch_intrinsics(intrinsics).to(omega)
    xy = normalized_grid(K, height, width)
    x, y = xy[:, 0], xy[:, 1]
    wx, wy, wz = (omega[:, i, None, None] for i in range(3))
    u = K[:, 0, None, None] * (x * y * wx - (1 + x * x) * wy + y * wz)
    v = K[:, 1, None, None] * ((1 + y * y) * wx - x * y * wy - x * wz)
    return torch.stack([u, v], dim=1)


@full_precision
def motion_field(t: Tensor, omega: Tensor, inv_depth: Tensor, intrinsics: Tensor) -> Tensor:
    """The full motion field ``v = ρ A t + B ω`` (paper eq. 2).

    Args:
        t: ``(B, 3)`` translation (m per frame); omega: ``(B, 3)`` rotation vector (rad per frame).
        inv_depth: ``(B, H, W)`` inverse depth ρ in m⁻¹ (0 for points at infinity).
        intrinsics: ``(B, 4)`` in pixels.

    Returns:
        ``(B, 2, H, W)`` pixels per frame.
    """
    height, width = inv_depth.shape[-2:]
    v_t = translational_field(t, intrinsics, height, width)
    v_w = rotational_field(omega, intrinsics, height, width)
    return inv_depth[:, None] * v_t + v_w


# --------------------------------------------------------------------------------------------
# Closed-form recovery of (t, ω) from fields
# --------------------------------------------------------------------------------------------


class FieldBasis:
    """A and B of one pixel grid with their least-squares pseudo-inverses, computed once.

    ``recover_translation`` solves ``min_t ‖A t - v_t‖²`` over all pixels and
    ``recover_rotation`` solves ``min_ω ‖B ω - v_ω‖²`` (paper eq. 11, ``t̃ = ṽ_t / A | ρ=1``).
    Use :func:`field_basis` to get a cached instance rather than building one per frame.

    Args:
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)`` in pixels; the matrices have its dtype.
        height, width: grid size.
        device: where the matrices live (default: the intrinsics' device). The pseudo-inverses
            are computed in float64 where the intrinsics are (the host, for
            :func:`recover_motion`) and then moved, so a GPU evaluation never solves on the GPU.
    """

    def __init__(
        self, intrinsics: Tensor, height: int, width: int, device: torch.device | None = None
    ) -> None:
        K = _as_batch_intrinsics(intrinsics)
        if K.shape[0] != 1:
            raise ValueError("FieldBasis describes one grid: pass a single (4,) intrinsics row")
        A, B = motion_matrices(K.double(), height, width)
        # (2N, 3) with the two components of each pixel stacked channel-first, matching a
        # (2, H, W) field flattened row-major.
        A = A[0].permute(2, 0, 1, 3).reshape(2 * height * width, 3)
        B = B[0].permute(2, 0, 1, 3).reshape(2 * height * width, 3)
        where = dict(device=K.device if device is None else device, dtype=K.dtype)
        self.A_pinv = torch.linalg.pinv(A).to(**where)
        self.B_pinv = torch.linalg.pinv(B).to(**where)
        self.A = A.to(**where)
        self.B = B.to(**where)
        self.height, self.width = height, width

    @full_precision
    def recover_translation(self, v_t: Tensor) -> Tensor:
        """``(B, 2, H, W)`` translational field at ρ = 1 → ``(B, 3)`` translation (m)."""
        return v_t.flatten(1) @ self.A_pinv.to(v_t).T

    @full_precision
    def recover_rotation(self, v_omega: Tensor) -> Tensor:
        """``(B, 2, H, W)`` rotational field → ``(B, 3)`` rotation vector (rad)."""
        return v_omega.flatten(1) @ self.B_pinv.to(v_omega).T


_BASIS_CACHE: OrderedDict[tuple, FieldBasis] = OrderedDict()
_BASIS_CACHE_SIZE = 64


def field_basis(
    intrinsics: Tensor, height: int, width: int, device: torch.device | None = None
) -> FieldBasis:
    """Cached :class:`FieldBasis` for one grid (keyed by intrinsics, size, device and dtype).

    Args:
        intrinsics: ``(4,)`` in pixels. Its values make the key: CPU intrinsics cost no device
            synchronisation, intrinsics on an accelerator one.
        device: where the basis is wanted (default: the intrinsics' device).
    """
    K = _as_batch_intrinsics(intrinsics)[0]
    device = K.device if device is None else torch.device(device)
    key = (*(round(k, 6) for k in K.tolist()), height, width, device, K.dtype)
    basis = _BASIS_CACHE.get(key)
    if basis is None:
        basis = FieldBasis(K, height, width, device=device)
        _BASIS_CACHE[key] = basis
        if len(_BASIS_CACHE) > _BASIS_CACHE_SIZE:
            _BASIS_CACHE.popitem(last=False)
    else:
        _BASIS_CACHE.move_to_end(key)
    return basis


@full_precision
def recover_motion(
    v_t: Tensor | None, v_omega: Tensor | None, intrinsics: Tensor
) -> tuple[Tensor | None, Tensor | None]:
    """Closed-form egomotion from predicted fields (paper eq. 11), batched.

    Samples that share intrinsics share one cached pseudo-inverse; a batch normally has one
    set of intrinsics, so this is a single matrix product. The product runs in float32 (the
    fields' dtype; float64 fields in float64) whatever the autocast around the call.

    The grouping by intrinsics reads their values on the host: intrinsics on the CPU (a batch's
    own before its transfer, which :class:`~mfg_lightning.models.mfg_module.MFGLitModule` keeps)
    cost no device synchronisation even when the fields are on a GPU; intrinsics on a GPU cost
    one per call.

    Args:
        v_t: ``(B, 2, H, W)`` translational field at unit inverse depth, or None.
        v_omega: ``(B, 2, H, W)`` rotational field, or None.
        intrinsics: ``(B, 4)`` or ``(4,)`` in pixels at the fields' resolution, on any device.

    Returns:
        ``(t, ω)``: ``(B, 3)`` each (None where the field was None).
    """
    ref = v_t if v_t is not None else v_omega
    if ref is None:
        raise ValueError("recover_motion needs at least one field")
    batch, _, height, width = ref.shape
    K = _as_batch_intrinsics(intrinsics).detach().to("cpu").to(ref.dtype)
    if K.shape[0] == 1:
        K = K.expand(batch, 4)
    unique, inverse = torch.unique(K, dim=0, return_inverse=True)
    if unique.shape[0] == 1:
        basis = field_basis(unique[0], height, width, device=ref.device)
        t = None if v_t is None else basis.recover_translation(v_t)
        w = None if v_omega is None else basis.recover_rotation(v_omega)
        return t, w
    t = None if v_t is None else v_t.new_empty(batch, 3)
    w = None if v_omega is None else v_omega.new_empty(batch, 3)
    for i, row in enumerate(unique):
        basis = field_basis(row, height, width, device=ref.device)
        idx = (inverse == i).nonzero(as_tuple=True)[0].to(ref.device)
        if t is not None:
            t[idx] = basis.recover_translation(v_t[idx])
        if w is not None:
            w[idx] = basis.recover_rotation(v_omega[idx])
    return t, w


# --------------------------------------------------------------------------------------------
# Exact reprojection (the slow, obvious counterpart of the motion field)
# --------------------------------------------------------------------------------------------


@full_precision
def backproject(depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Back-project every pixel with its depth.

    Args:
        depth: ``(B, H, W)`` depth along the camera z axis in metres.
        intrinsics: ``(B, 4)`` in pixels.

    Returns:
        ``(B, H, W, 3)`` points in camera coordinates (metres).
    """
    height, width = depth.shape[-2:]
    xy = normalized_grid(_as_batch_intrinsics(intrinsics).to(depth), height, width)
    ones = torch.ones_like(depth)
    rays = torch.stack([xy[:, 0].expand_as(depth), xy[:, 1].expand_as(depth), ones], dim=-1)
    return rays * depth[..., None]


@full_precision
def project(points: Tensor, intrinsics: Tensor) -> Tensor:
    """Pinhole projection.

    Args:
        points: ``(B, H, W, 3)`` camera coordinates (metres), z > 0.
        intrinsics: ``(B, 4)`` in pixels.

    Returns:
        ``(B, H, W, 2)`` pixel coordinates ``(u, v)``.
    """
    K = _as_batch_intrinsics(intrinsics).to(points)
    z = points[..., 2].clamp_min(_EPS)
    u = K[:, 0, None, None] * points[..., 0] / z + K[:, 2, None, None]
    v = K[:, 1, None, None] * points[..., 1] / z + K[:, 3, None, None]
    return torch.stack([u, v], dim=-1)


@full_precision
def reprojection_flow(
    depth: Tensor, pose: Tensor, intrinsics: Tensor, point_motion: Tensor | None = None
) -> Tensor:
    """Exact optical flow of a camera move: back-project, move, re-project.

    Args:
        depth: ``(B, H, W)`` depth of frame k in metres.
        pose: ``(B, 4, 4)`` relative pose ``T_k,k+1`` (camera k+1 in camera k).
        intrinsics: ``(B, 4)`` in pixels.
        point_motion: optional ``(B, H, W, 3)`` displacement of each scene point between the two
            frames, in camera-k coordinates (metres): independently moving objects.

    Returns:
        ``(B, 2, H, W)`` flow from frame k to frame k+1 in pixels.
    """
    points = backproject(depth, intrinsics)
    if point_motion is not None:
        points = points + point_motion
    R = pose[:, :3, :3].to(points)
    t = pose[:, :3, 3].to(points)
    # X_{k+1} = R^T (X_k - t): the inverse of T_k,k+1 maps camera-k points into camera k+1.
    moved = torch.einsum("bji,bhwj->bhwi", R, points - t[:, None, None, :])
    target = project(moved, intrinsics)
    height, width = depth.shape[-2:]
    u = torch.arange(width, device=depth.device, dtype=points.dtype)
    v = torch.arange(height, device=depth.device, dtype=points.dtype)
    grid = torch.stack(torch.meshgrid(u, v, indexing="xy"), dim=-1)
    return (target - grid).permute(0, 3, 1, 2)


@full_precision
def scale_intrinsics(intrinsics: Tensor, scale_x: float, scale_y: float) -> Tensor:
    """Intrinsics of a resized image.

    Pixel centres map as ``u' = (u + 0.5) · s - 0.5``, so ``cx' = (cx + 0.5) · s - 0.5``.

    Args:
        intrinsics: ``(..., 4)`` ``(fx, fy, cx, cy)`` in pixels of the original image.
        scale_x, scale_y: new width / old width and new height / old height.

    Returns:
        ``(..., 4)`` in pixels of the resized image.
    """
    fx, fy, cx, cy = intrinsics.unbind(-1)
    return torch.stack(
        [fx * scale_x, fy * scale_y, (cx + 0.5) * scale_x - 0.5, (cy + 0.5) * scale_y - 0.5], -1
    )
