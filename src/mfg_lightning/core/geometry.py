"""Continuous egomotion geometry: A(p), B(p), motion fields, closed-form recovery, SE(3).

This module is the single home of the motion-field geometry of the paper's section 3. Datasets,
losses, the Lightning module, metrics and object-motion extraction call it; none re-derives it.
Every function is batched over a leading dimension ``B`` and works on any device, in float32 or
float64: float16 / bfloat16 arguments are widened to float32 and autocast is turned off inside
(:func:`full_precision`), so a caller under ``trainer.precision=bf16-mixed`` gets float32 answers.

Conventions
-----------
* **Camera axes**: x right, y down, z forward (KITTI, OpenCV).
* **Pixels**: ``u`` (column) and ``v`` (row) with integer values at pixel centres, so the principal
  point ``(cx, cy)`` is in the same coordinates as KITTI's calibration. Intrinsics are passed as a
  tensor ``(B, 4)`` holding ``(fx, fy, cx, cy)`` in pixels *at the resolution of the field*.
* **Fields** are tensors ``(B, 2, H, W)`` of image velocities in pixels per frame, channel 0 the
  horizontal (u) and channel 1 the vertical (v) component.
* **Poses**: a pose ``T_world_cam`` is a camera-to-world 4×4 matrix. The relative motion from frame
  k to k+1 is ``T_k,k+1 = T_world_cam(k)^-1 · T_world_cam(k+1)``: the camera at k+1 expressed in
  the camera at k (``docs/protocols.md``).
* **Egomotion (t, ω)**: the camera's own translation ``t`` (metres per frame) and rotation vector
  ``ω`` (radians per frame), both in the coordinates of the camera at k. A relative pose
  ``T_k,k+1 = [R | t]`` converts to ``(t, ω)`` with ``ω = log(R)`` (:func:`pose_to_motion`), and
  back with ``R = exp(ω)`` (:func:`motion_to_pose`). Driving forward gives ``t_z > 0``.
* **Motion field**: a static point ``P`` (camera-k coordinates) seen by a camera moving with
  ``(t, ω)`` moves, relative to the camera, by ``-t - ω × P``. Its image velocity at normalised
  coordinates ``(x, y) = ((u - cx)/fx, (v - cy)/fy)`` and inverse depth ``ρ = 1/Z`` is::

      v = ρ A t + B ω,   A = [[-1,  0, x],        B = [[ x y,   -(1 + x²),  y],
                              [ 0, -1, y]]             [ 1 + y², -x y,     -x]]

  then scaled to pixels by ``(fx, fy)``. The paper prints A and B with the opposite overall sign,
  which is the same field written for the motion of the scene relative to the camera,
  ``(t, ω)_paper = -(t, ω)``; we use the camera's own motion so that recovered parameters read
  as egomotion (forward driving: ``t_z > 0``). The field is the first-order (small-motion)
  approximation of the exact reprojection flow (:func:`reprojection_flow`); the difference
  shrinks quadratically with the motion (tested).
* **Translational field at unit depth** (``ρ = 1`` m⁻¹): ``v_t = A t``; the rotational field is
  ``v_ω = B ω``; the full field is ``v = ρ v_t + v_ω``.
"""

from __future__ import annotations

import contextlib
import functools
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import torch
from torch import Tensor

__all__ = [
    "FieldBasis",
    "autocast_devices",
    "backproject",
    "field_basis",
    "float32_math",
    "full_precision",
    "invert_pose",
    "motion_field",
    "motion_matrices",
    "motion_to_pose",
    "normalized_grid",
    "pose_to_motion",
    "project",
    "recover_motion",
    "relative_pose",
    "reprojection_flow",
    "rotation_angle",
    "rotational_field",
    "scale_intrinsics",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_log",
    "to_float32",
    "trajectory_from_motions",
    "translational_field",
]

_EPS = 1e-8


# --------------------------------------------------------------------------------------------
# Precision: geometry runs in float32 (or float64) whatever the autocast around it
# --------------------------------------------------------------------------------------------

#: Device types on which ``torch.autocast`` can be active.
_AUTOCAST_DEVICES = ("cpu", "cuda", "mps", "xpu")
#: The dtypes that :func:`to_float32` widens.
_LOW_PRECISION = (torch.float16, torch.bfloat16)

F = TypeVar("F", bound=Callable[..., Any])


def autocast_devices() -> tuple[str, ...]:
    """The device types on which ``torch.autocast`` is active here (empty outside autocast)."""
    return tuple(d for d in _AUTOCAST_DEVICES if torch.is_autocast_enabled(d))


@contextlib.contextmanager
def float32_math() -> Iterator[None]:
    """Turn autocast off, on every device where it is on, for the body.

    Under ``trainer.precision=bf16-mixed`` (or ``16-mixed``) Lightning runs the whole step under
    autocast, which would run every matrix product of the body (the recovery's pseudo-inverse
    product, ``so3_exp``'s ``W @ W``, ``reprojection_flow``'s einsum) in the low precision. Inside
    this context ops run in their inputs' dtype; outside autocast it does nothing.
    """
    with contextlib.ExitStack() as stack:
        for device in autocast_devices():
            stack.enter_context(torch.autocast(device, enabled=False))
        yield


def to_float32(x: Any) -> Any:
    """``x`` as float32 if it is a float16 / bfloat16 tensor; anything else (float32, float64,
    integer and bool tensors, non-tensors) unchanged."""
    return x.float() if isinstance(x, Tensor) and x.dtype in _LOW_PRECISION else x


def full_precision(fn: F) -> F:
    """Decorator: run ``fn`` in float32 whatever the caller's precision.

    Inside, autocast is off (:func:`float32_math`) and float16 / bfloat16 tensor arguments are
    widened to float32 (:func:`to_float32`); float32 and float64 arguments are passed as they are,
    so without autocast and without low-precision arguments ``fn`` runs exactly as undecorated (the
    check costs about a microsecond). Used by the geometry, the losses, object motion and the
    metrics, so that any caller under autocast gets float32 answers: with its intrinsics cast to
    bfloat16 (fx 74.145 → 74.0) the recovery of ``(t, ω)`` from exact fields erred by up to
    2.2e-3 m and 8.5e-5 rad; decorated, it gives float32's answer to 1e-5 m and 1e-7 rad
    (``tests/test_precision.py``).
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        devices = autocast_devices()
        low = any(
            isinstance(a, Tensor) and a.dtype in _LOW_PRECISION for a in (*args, *kwargs.values())
        )
        if not devices and not low:
            return fn(*args, **kwargs)
        args = tuple(to_float32(a) for a in args)
        kwargs = {k: to_float32(v) for k, v in kwargs.items()}
        with float32_math():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


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


# --------------------------------------------------------------------------------------------
# SO(3) and SE(3)
# --------------------------------------------------------------------------------------------


def _hat(w: Tensor) -> Tensor:
    """``(..., 3)`` vector → ``(..., 3, 3)`` skew-symmetric matrix ``[w]×``."""
    zero = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], dim=-1).reshape(
        *w.shape[:-1], 3, 3
    )


def _sinc_terms(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``sin θ/θ``, ``(1 - cos θ)/θ²`` and ``(θ - sin θ)/θ³`` with Taylor series near 0."""
    small = theta < 1e-4
    safe = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    a = torch.where(small, 1 - t2 / 6, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(safe)) / (safe * safe))
    c = torch.where(small, 1 / 6 - t2 / 120, (safe - torch.sin(safe)) / safe**3)
    return a, b, c


@full_precision
def so3_exp(omega: Tensor) -> Tensor:
    """Rodrigues: rotation vector ``(..., 3)`` (rad) → rotation matrix ``(..., 3, 3)``."""
    theta = omega.norm(dim=-1)[..., None, None]
    a, b, _ = _sinc_terms(theta)
    W = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(W)
    return eye + a * W + b * (W @ W)


@full_precision
def so3_log(R: Tensor) -> Tensor:
    """Rotation matrix ``(..., 3, 3)`` → rotation vector ``(..., 3)`` (rad), angle in [0, π]."""
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((trace - 1) / 2).clamp(-1.0, 1.0)
    vee = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        dim=-1,
    )
    sin = 0.5 * vee.norm(dim=-1)
    theta = torch.atan2(sin, cos)
    small = theta < 1e-4
    factor = torch.where(
        small, 0.5 + theta**2 / 12, theta / (2 * torch.sin(theta).clamp_min(1e-12))
    )
    w = vee * factor[..., None]
    # Near π the antisymmetric part vanishes: read the axis from the symmetric part instead.
    # Computed for every rotation and selected with where: asking whether any is near π would
    # be a device synchronisation in every training step (the ground-truth poses pass here).
    near_pi = theta > torch.pi - 1e-3
    S = (R + R.transpose(-1, -2)) / 2 - cos[..., None, None] * torch.eye(
        3, dtype=R.dtype, device=R.device
    )
    col = S.diagonal(dim1=-2, dim2=-1).argmax(dim=-1)
    axis = torch.gather(S, -1, col[..., None, None].expand(*S.shape[:-1], 1)).squeeze(-1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # Choose the sign consistent with the (small) antisymmetric part.
    sign = torch.where((axis * vee).sum(-1) < 0, -1.0, 1.0).to(R.dtype)
    return torch.where(near_pi[..., None], axis * (theta * sign)[..., None], w)


@full_precision
def rotation_angle(R: Tensor) -> Tensor:
    """Angle of a rotation matrix ``(..., 3, 3)`` in radians: ``arccos(clip((tr R − 1)/2))``."""
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    return torch.arccos(((trace - 1) / 2).clamp(-1.0, 1.0))


def _make_pose(R: Tensor, t: Tensor) -> Tensor:
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


@full_precision
def se3_exp(xi: Tensor) -> Tensor:
    """Twist ``(..., 6)`` = ``(v, ω)`` → pose ``(..., 4, 4)`` (the SE(3) exponential)."""
    v, w = xi[..., :3], xi[..., 3:]
    _, b, c = _sinc_terms(w.norm(dim=-1)[..., None, None])
    W = _hat(w)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    V = eye + b * W + c * (W @ W)  # the left Jacobian of SO(3)
    return _make_pose(so3_exp(w), (V @ v[..., None])[..., 0])


@full_precision
def se3_log(T: Tensor) -> Tensor:
    """Pose ``(..., 4, 4)`` → twist ``(..., 6)`` = ``(v, ω)`` (the SE(3) logarithm)."""
    w = so3_log(T[..., :3, :3])
    theta = w.norm(dim=-1)[..., None, None]
    a, b, _ = _sinc_terms(theta)
    W = _hat(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand_as(W)
    # V^-1 = I - W/2 + (1 - a / (2 b)) / θ² W²  (series near 0: 1/12).
    small = theta < 1e-4
    safe = torch.where(small, torch.ones_like(theta), theta)
    coef = torch.where(small, torch.full_like(theta, 1 / 12), (1 - a / (2 * b)) / (safe * safe))
    V_inv = eye - 0.5 * W + coef * (W @ W)
    v = (V_inv @ T[..., :3, 3:4])[..., 0]
    return torch.cat([v, w], dim=-1)


@full_precision
def invert_pose(T: Tensor) -> Tensor:
    """Inverse of rigid transforms ``(..., 4, 4)`` (exact, using Rᵀ)."""
    R = T[..., :3, :3].transpose(-1, -2)
    t = -(R @ T[..., :3, 3:4])[..., 0]
    return _make_pose(R, t)


@full_precision
def relative_pose(T_world_a: Tensor, T_world_b: Tensor) -> Tensor:
    """``T_a,b = T_world_a^-1 · T_world_b``: camera b expressed in camera a. ``(..., 4, 4)``."""
    return invert_pose(T_world_a) @ T_world_b


@full_precision
def pose_to_motion(T: Tensor) -> tuple[Tensor, Tensor]:
    """Relative pose ``T_k,k+1`` ``(..., 4, 4)`` → egomotion ``(t, ω)``, ``(..., 3)`` each.

    ``t`` is the translation column (metres) and ``ω = log(R)`` (radians); the module docstring
    gives the frames.
    """
    return T[..., :3, 3], so3_log(T[..., :3, :3])


@full_precision
def motion_to_pose(t: Tensor, omega: Tensor) -> Tensor:
    """Egomotion ``(t, ω)`` ``(..., 3)`` each → relative pose ``T_k,k+1`` ``(..., 4, 4)``."""
    return _make_pose(so3_exp(omega), t)


@full_precision
def trajectory_from_motions(relative: Tensor) -> Tensor:
    """Compose relative poses into a trajectory starting at the identity.

    ``T(0) = I``, ``T(k+1) = T(k) · T_k,k+1`` (``docs/protocols.md``).

    Args:
        relative: ``(..., N, 4, 4)`` relative poses ``T_k,k+1`` for k = 0 … N−1.

    Returns:
        ``(..., N + 1, 4, 4)`` camera-to-world poses in the frame of the first camera.
    """
    eye = torch.eye(4, dtype=relative.dtype, device=relative.device)
    poses = [eye.expand(*relative.shape[:-3], 4, 4)]
    for k in range(relative.shape[-3]):
        poses.append(poses[-1] @ relative[..., k, :, :])
    return torch.stack(poses, dim=-3)


# --------------------------------------------------------------------------------------------
# Cleaning up poses read from files
# --------------------------------------------------------------------------------------------


def _det3(M: Tensor) -> Tensor:
    """Determinant of ``(..., 3, 3)`` matrices as the triple product of their rows."""
    return (torch.linalg.cross(M[..., 0, :], M[..., 1, :], dim=-1) * M[..., 2, :]).sum(-1)


@full_precision
def project_to_se3(T: Tensor) -> Tensor:
    """The nearest rigid transform: rotation block projected onto SO(3), bottom row reset.

    Pose files store rotations to about seven significant digits (KITTI writes ``%e``), so
    ``RᵀR`` misses the identity by ~1e-7. The rotation angle ``arccos((tr R − 1) / 2)`` used by RPE
    and the KITTI drift is steep near zero and turns that rounding into a spurious error of
    ~5e-4 rad between two *identical* KITTI trajectories; projecting first removes it. Exact
    rotations come back unchanged up to rounding.

    The projection is the closest rotation in the Frobenius norm, ``U diag(1, 1, det(U Vᵀ)) Vᵀ``
    from the SVD ``R = U S Vᵀ`` (the orthogonal polar factor, with a reflection turned into the
    nearest proper rotation). The translation column is kept as it is.

    Args:
        T: ``(..., 4, 4)`` approximately rigid transforms (any float dtype).

    Returns:
        ``(..., 4, 4)`` rigid transforms with ``RᵀR = I``, ``det R = +1`` and bottom row
        ``(0, 0, 0, 1)``.
    """
    U, _, Vh = torch.linalg.svd(T[..., :3, :3])
    # det(U Vᵀ) = det U · det Vᵀ = ±1, each a triple product: linalg.det and a batched matmul
    # are an order of magnitude slower on thousands of 3×3 blocks.
    det = _det3(U) * _det3(Vh)
    # where, not sign: a singular block (det 0) still has to come back as a proper rotation.
    flip = torch.where(det < 0, -torch.ones_like(det), torch.ones_like(det))
    U = torch.cat([U[..., :2], U[..., 2:] * flip[..., None, None]], dim=-1)
    return _make_pose(U @ Vh, T[..., :3, 3])


__all__ += ["project_to_se3"]
