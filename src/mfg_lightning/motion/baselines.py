"""Classical egomotion from optic flow: the methods a user would otherwise run, on MFG's inputs.

Each function takes the same batch MFG takes (flow ``(B, 2, H, W)`` in pixels, its validity mask
and the intrinsics) and returns the camera's egomotion ``(t, ω)`` ``(B, 3)`` each in the
conventions of :mod:`mfg_lightning.core.geometry` (the camera's own translation in metres and
rotation
vector in radians, camera-k coordinates; driving forward gives ``t_z > 0``), so that their
predictions are scored by exactly the code that scores MFG (``bench/accuracy.py``).

* :func:`essential_matrix_motion`: the discrete two-view method. Flow vectors on a pixel grid are
  point correspondences; OpenCV's five-point essential matrix inside RANSAC (or one of its USAC
  variants such as MAGSAC++; ``cv2.findEssentialMat``) and the cheirality check
  (``cv2.recoverPose``) give the rotation and the direction of the translation.
* :func:`continuous_least_squares`: the continuous method of the paper's section 3. The motion
  field is ``v = ρ A t + B ω`` (eq. 2, with ``A`` and ``B`` from
  :func:`mfg_lightning.core.geometry.motion_matrices`). Minimising ``‖ρ A t + B ω − v̂‖²`` over the
  per-pixel inverse depths ρ in closed form leaves, at every pixel, the component of
  ``B ω − v̂`` along the unit normal of ``A t`` (eq. 5, normalised as in Bruss and Horn 1983,
  "Passive navigation", which makes it the exact least-squares objective after eliminating ρ;
  the paper's eq. 5 writes the un-normalised ``A^⊥ t``). For a fixed direction of ``t`` that
  residual is linear in ``ω``, so ``ω(t)`` is a 3 × 3 linear solve and the objective ``E(t)`` is
  a function on the sphere of directions only. It is minimised by an exhaustive search over a
  Fibonacci grid on the half sphere (``t`` and ``−t`` give the same residual) followed by a
  shrinking pattern search around the best direction; the sign of ``t`` is the one that puts
  most points in front of the camera (ρ > 0). Optional iteratively reweighted least squares
  (Cauchy weights, scale from the median absolute residual) makes it robust to outliers and
  moving objects, in the spirit of Jaegle et al. 2016 (whose exact algorithm this is not).
* :func:`oracle_motion`: the floor. The exact translational (ρ = 1) and rotational fields of the
  ground-truth motion, turned back into ``(t, ω)`` by the same closed form MFG's predictions go
  through (:func:`mfg_lightning.core.geometry.recover_motion`): the error of the pipeline itself
  when
  the fields are perfect (float rounding only).

Scale. A single camera observes the translation only up to scale (the flow is unchanged when the
scene and ``t`` are scaled together): both classical methods return a unit direction. As
monocular methods are evaluated (e.g. ORB-SLAM and the learned methods in the paper's Table 1),
their translation is given the length of the ground-truth translation (``translation_norm``);
the ATE of a 5-frame snippet then also aligns the scale of every snippet by least squares. MFG
is not rescaled: it predicts metric translation learned from the training poses.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from mfg_lightning.core import geometry

__all__ = [
    "VERSION",
    "continuous_least_squares",
    "essential_matrix_motion",
    "fibonacci_hemisphere",
    "oracle_motion",
]

#: The version of these methods, recorded in every stage result of the reproduction study
#: (``baselines_version``), so that a result computed before a fix is known from the result
#: itself, in a checkout without git history too. 1: before the essential-matrix cheirality fix
#: (commit 63f9c3b: :func:`_cheirality_pose` counts every inlier); 2: with it. Raise it with
#: every change that moves a method's numbers.
VERSION = 2


def _check_flow(flow: Tensor, valid: Tensor | None, intrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """Validate shapes; return the float64 flow and a ``(B, H, W)`` bool mask."""
    if flow.dim() != 4 or flow.shape[1] != 2:
        raise ValueError(f"flow must be (B, 2, H, W) pixels, got shape {tuple(flow.shape)}")
    batch, _, height, width = flow.shape
    if intrinsics.shape not in ((batch, 4), (4,)):
        raise ValueError(
            f"intrinsics must be (B, 4) or (4,) (fx, fy, cx, cy), got {tuple(intrinsics.shape)}"
        )
    flow = flow.detach().to("cpu", torch.float64)
    if valid is None:
        valid = torch.ones(batch, height, width, dtype=torch.bool)
    mask = valid.detach().to("cpu").bool() & torch.isfinite(flow).all(dim=1)
    return flow, mask


def _batch_intrinsics(intrinsics: Tensor, batch: int) -> Tensor:
    K = intrinsics.detach().to("cpu", torch.float64)
    return K.expand(batch, 4) if K.dim() == 1 else K


def _scaled(direction: Tensor, translation_norm: Tensor | None) -> Tensor:
    """Give unit translations ``(B, 3)`` the ground-truth length ``(B,)`` (module docstring)."""
    if translation_norm is None:
        return direction
    return direction * translation_norm.detach().to(direction)[:, None]


# --------------------------------------------------------------------------------------------
# Oracle
# --------------------------------------------------------------------------------------------


def oracle_motion(
    pose: Tensor, intrinsics: Tensor, height: int, width: int
) -> tuple[Tensor, Tensor]:
    """``(t, ω)`` recovered from the exact motion fields of the true motion: the error floor.

    Args:
        pose: ``(B, 4, 4)`` true relative pose ``T_k,k+1``; its dtype is the one the fields are
            built and recovered in (float32, as MFG's fields, gives the float32 floor).
        intrinsics: ``(B, 4)`` or ``(4,)`` pixels at ``height × width``.

    Returns:
        ``(t, ω)``, ``(B, 3)`` each: metres and radians per frame.
    """
    t, w = geometry.pose_to_motion(pose)
    K = intrinsics.to(pose)
    v_t = geometry.translational_field(t, K, height, width)
    v_w = geometry.rotational_field(w, K, height, width)
    t_hat, w_hat = geometry.recover_motion(v_t, v_w, K)
    assert t_hat is not None and w_hat is not None  # both fields were given
    return t_hat, w_hat


# --------------------------------------------------------------------------------------------
# Essential matrix + RANSAC (OpenCV)
# --------------------------------------------------------------------------------------------


def essential_matrix_motion(
    flow: Tensor,
    intrinsics: Tensor,
    valid: Tensor | None = None,
    translation_norm: Tensor | None = None,
    *,
    method: str = "RANSAC",
    pixel_stride: int = 2,
    threshold: float = 0.5,
    confidence: float = 0.999,
    max_iters: int = 1000,
    seed: int = 0,
) -> tuple[Tensor, Tensor]:
    """Egomotion from flow correspondences with the essential matrix and RANSAC (OpenCV).

    Every ``pixel_stride``-th pixel with valid flow gives a correspondence
    ``(u, v) → (u + f_u, v + f_v)``. ``cv2.findEssentialMat`` (five-point solver in RANSAC) and
    ``cv2.recoverPose`` (the decomposition with most points in front of both cameras) give
    OpenCV's ``(R, t)`` with ``X₂ = R X₁ + t``; in this package's convention the relative pose
    is ``T_k,k+1 = [Rᵀ | −Rᵀ t]``.

    The cheirality vote counts every inlier however far, and of stacked solutions keeps the one
    with the most points in front (:func:`_cheirality_pose` says why).

    Args:
        flow: ``(B, 2, H, W)`` flow from frame k to k+1, pixels.
        intrinsics: ``(B, 4)`` or ``(4,)`` ``(fx, fy, cx, cy)`` pixels at the flow's resolution.
        valid: ``(B, H, W)`` pixels whose flow may be used (None: all finite pixels).
        translation_norm: ``(B,)`` length given to the unit translation (the ground truth's, as
            monocular methods are evaluated); None keeps unit length.
        method: the robust estimator, a ``cv2`` constant's name: ``"RANSAC"`` (the classic
            one), or one of OpenCV's USAC variants, e.g. ``"USAC_MAGSAC"`` (MAGSAC++, with local
            optimisation and a final least-squares fit to the inliers: markedly more accurate
            on dense noisy flow).
        pixel_stride: sample every n-th row and column.
        threshold: RANSAC inlier distance to the epipolar line, pixels.
        confidence, max_iters: RANSAC's confidence level and iteration cap.
        seed: seed of OpenCV's RNG (RANSAC's samples), set before every frame, for results
            that are repeatable and independent of the batching.

    Returns:
        ``(t, ω)``, ``(B, 3)`` float64 each. A frame with fewer than 5 valid correspondences, or
        whose essential matrix cannot be estimated (no motion), gets ``t = 0``, ``ω = 0``.
    """
    import cv2

    flow, mask = _check_flow(flow, valid, intrinsics)
    batch, _, height, width = flow.shape
    K = _batch_intrinsics(intrinsics, batch)
    estimator = getattr(cv2, method, None)
    if not isinstance(estimator, int):
        raise ValueError(
            f"method must name a cv2 robust estimator (RANSAC, USAC_*), got {method!r}"
        )
    rows = torch.arange(0, height, pixel_stride, dtype=torch.float64)
    cols = torch.arange(0, width, pixel_stride, dtype=torch.float64)
    grid_v, grid_u = torch.meshgrid(rows, cols, indexing="ij")
    src_all = torch.stack([grid_u, grid_v], dim=-1).reshape(-1, 2)
    sub = (slice(None), slice(None, None, pixel_stride), slice(None, None, pixel_stride))
    t_out = torch.zeros(batch, 3, dtype=torch.float64)
    w_out = torch.zeros(batch, 3, dtype=torch.float64)
    for b in range(batch):
        keep = mask[b][sub[1:]].reshape(-1)
        src = src_all[keep]
        dst = src + flow[b][sub].reshape(2, -1).T[keep]
        if src.shape[0] < 5:
            continue
        fx, fy, cx, cy = K[b].tolist()
        cam = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        p1, p2 = src.numpy(), dst.numpy()
        # Re-seeded per frame: a frame's result does not depend on the batch it came in.
        cv2.setRNGSeed(seed)
        try:
            E, inliers = cv2.findEssentialMat(
                p1,
                p2,
                cam,
                method=estimator,
                prob=confidence,
                threshold=threshold,
                maxIters=max_iters,
            )
        except cv2.error as err:
            # OpenCV >= 5.1 asserts on a degenerate sample (e.g. no point moves: the 5-point
            # solver's polynomial vanishes) where 5.0 returned no solution; both mean no estimate.
            if "solvePoly" not in str(err):
                raise
            continue
        # A missing solution means no motion to find.
        if E is None or E.shape[0] < 3:
            continue
        R, t = _cheirality_pose(E, p1, p2, cam, inliers)
        R_rel = torch.from_numpy(R).T
        t_rel = -(R_rel @ torch.from_numpy(t).reshape(3))
        t_out[b] = t_rel / t_rel.norm().clamp_min(1e-12)
        w_out[b] = geometry.so3_log(R_rel)
    return _scaled(t_out, translation_norm), w_out


def _cheirality_pose(
    E: np.ndarray, p1: np.ndarray, p2: np.ndarray, cam: np.ndarray, inliers: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's ``(R, t)`` of the decomposition of ``E`` (one or several stacked 3 × 3 solutions)
    that puts the most inliers in front of both cameras, the first of those that tie.

    Without a ``distanceThresh``, ``cv2.recoverPose`` leaves out the points it triangulates
    beyond 50 baselines, as points at infinity. A slow camera can have its whole scene that far:
    at 0.06 m per frame, 50 baselines is 3 m (KITTI 10 slowing down near frame 1150, or its
    first frame, 0.13 m before a backdrop at 655 m). No point is then left, the four
    decompositions tie at zero and OpenCV returns the first one, with the rotation turned by π
    or the translation reversed. Far points are not at infinity: exact flow gives each one's
    side. Noisy flow's far points split between ``t`` and ``−t`` of the same rotation, so the
    near points still decide.

    With exactly five correspondences the five-point solver's solutions (up to ten) all come
    back stacked; five points can fit several of them exactly, so such an estimate may still be
    wrong.
    """
    import cv2

    best: tuple[int, np.ndarray, np.ndarray] | None = None
    for k in range(E.shape[0] // 3):
        # No distance limit: with the default 50 baselines a slow pair in a far scene keeps no
        # point, and the vote between the four decompositions is a tie at zero (the docstring).
        # recoverPose also writes its mask: a copy for every solution.
        mask = None if inliers is None else inliers.copy()
        good, R, t = cv2.recoverPose(
            E[3 * k : 3 * k + 3], p1, p2, cam, distanceThresh=np.inf, mask=mask
        )[:3]
        if best is None or good > best[0]:
            best = (good, R, t)
    assert best is not None  # E has at least one solution (the caller checks)
    return best[1], best[2]


# --------------------------------------------------------------------------------------------
# Continuous least squares (section 3)
# --------------------------------------------------------------------------------------------


def fibonacci_hemisphere(count: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """Nearly uniform unit vectors on the half sphere ``z ≥ 0`` (a golden-angle spiral).

    Returns:
        ``(count, 3)``; neighbouring points are about ``sqrt(2π / count)`` radians apart.
    """
    k = torch.arange(count, dtype=dtype)
    z = 1.0 - (k + 0.5) / count
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    phi = k * (math.pi * (3.0 - math.sqrt(5.0)))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


class _ContinuousProblem:
    """The continuous objective of one frame as moment sums, so any direction costs O(1).

    With ``n_i = P A_i t`` (``P`` the 90° rotation) the residual of pixel ``i`` after the best
    ρ_i is ``n_iᵀ (B_i ω − v̂_i) / ‖A_i t‖ = (tᵀ C_i ω − tᵀ q_i) / ‖A_i t‖`` with
    ``C_i = A_iᵀ Pᵀ B_i`` (3 × 3) and ``q_i = A_iᵀ Pᵀ v̂_i`` (3). For per-pixel weights ``w_i``
    fixed, the weighted sum of squares is a quartic form in ``t`` and quadratic in ``ω``: its
    Gram matrix ``H(t)``, right-hand side ``g(t)`` and constant ``E₀(t)`` are contractions of
    ``t`` with the moment tensors ``Q = Σ w C ⊗ C``, ``R = Σ w C ⊗ q`` and ``S = Σ w q qᵀ``,
    summed once over the pixels. The normalisation by ``‖A_i t‖²`` (which makes the sum the exact
    least-squares objective after eliminating ρ) is carried by the weights, re-evaluated at the
    current direction and iterated to a fixed point as in Zhang and Tomasi 1999.

    Args:
        A, B: ``(N, 2, 3)`` motion matrices of the N used pixels (pixel units).
        flow: ``(N, 2)`` observed flow, pixels.
    """

    def __init__(self, A: Tensor, B: Tensor, flow: Tensor) -> None:
        self.A, self.B, self.flow = A, B, flow
        # Pᵀ x = (x_1, −x_0) for P the rotation by +90°.
        pt_b = torch.stack([B[:, 1], -B[:, 0]], dim=1)
        pt_v = torch.stack([flow[:, 1], -flow[:, 0]], dim=1)
        self.C = torch.einsum("nki,nkj->nij", A, pt_b)  # (N, 3, 3)
        self.q = torch.einsum("nki,nk->ni", A, pt_v)  # (N, 3)
        self.set_weights(torch.ones(flow.shape[0], dtype=flow.dtype))

    def set_weights(self, weights: Tensor) -> None:
        """Per-pixel weights ``(N,)``: the moment sums are recomputed once here."""
        Cw = self.C * weights[:, None, None]
        self.Q = torch.einsum("nlj,nmk->jklm", Cw, self.C)
        self.R = torch.einsum("nlj,nm->jlm", Cw, self.q)
        self.S = torch.einsum("nl,nm->lm", self.q * weights[:, None], self.q)

    def solve(self, T: Tensor) -> tuple[Tensor, Tensor]:
        """Best ``ω`` ``(G, 3)`` and the objective ``(G,)`` for every direction ``T`` ``(G, 3)``."""
        H = torch.einsum("jklm,gl,gm->gjk", self.Q, T, T)
        g = torch.einsum("jlm,gl,gm->gj", self.R, T, T)
        e0 = torch.einsum("lm,gl,gm->g", self.S, T, T)
        # A tiny ridge keeps the 3 × 3 system solvable for degenerate pixel sets.
        ridge = 1e-12 * H.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30)
        omega = torch.linalg.solve(H + ridge[:, None, None] * torch.eye(3, dtype=H.dtype), g)
        return omega, e0 - (g * omega).sum(-1)

    def residuals(self, t: Tensor, omega: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """For one direction ``t`` ``(3,)`` and its ``ω``: the perpendicular residuals ``(N,)``
        in pixels, ``‖A_i t‖²`` ``(N,)`` and ``A_i t · (v̂_i − B_i ω)`` ``(N,)``, whose sign is
        the sign of ρ_i."""
        a = self.A @ t  # (N, 2)
        length2 = (a * a).sum(-1)
        perp = (self.C @ omega) @ t - self.q @ t
        along = (a * (self.flow - self.B @ omega)).sum(-1)
        return perp / length2.clamp_min(1e-18).sqrt(), length2, along


def _search(problem: _ContinuousProblem, grid: Tensor, refine_steps: int) -> tuple[Tensor, Tensor]:
    """Exhaustive search on ``grid`` then a shrinking 5 × 5 pattern search on the sphere."""
    omega, energy = problem.solve(grid)
    best = int(energy.argmin())
    t, w, e = grid[best], omega[best], energy[best]
    # Start at about the grid spacing; each round keeps the best of a 5 × 5 tangent-plane
    # pattern and shrinks it, so the direction converges geometrically.
    step = math.sqrt(2.0 * math.pi / grid.shape[0])
    offsets = torch.linspace(-1.0, 1.0, 5, dtype=grid.dtype)
    du, dv = torch.meshgrid(offsets, offsets, indexing="ij")
    du, dv = du.reshape(-1), dv.reshape(-1)
    for _ in range(refine_steps):
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=t.dtype)
        if abs(float(t[0])) > 0.9:
            helper = torch.tensor([0.0, 1.0, 0.0], dtype=t.dtype)
        e1 = torch.linalg.cross(t, helper)
        e1 = e1 / e1.norm()
        e2 = torch.linalg.cross(t, e1)
        cand = t[None] + step * (du[:, None] * e1 + dv[:, None] * e2)
        cand = cand / cand.norm(dim=-1, keepdim=True)
        omega, energy = problem.solve(cand)
        i = int(energy.argmin())
        if energy[i] < e:
            t, w, e = cand[i], omega[i], energy[i]
        step *= 0.4
    return t, w


def continuous_least_squares(
    flow: Tensor,
    intrinsics: Tensor,
    valid: Tensor | None = None,
    translation_norm: Tensor | None = None,
    *,
    pixel_stride: int = 2,
    grid_size: int = 400,
    refine_steps: int = 8,
    normalize_iterations: int = 6,
    robust: bool = False,
) -> tuple[Tensor, Tensor]:
    """Egomotion by least squares on the continuous motion-field equations, ρ eliminated.

    Solves ``min_{t, ω, ρ} ‖ρ A t + B ω − v̂‖²`` (the paper's eq. 4) as described in the module
    docstring: ρ in closed form per pixel, ω in closed form per direction of t, the direction by
    grid and pattern search. The first search minimises the paper's eq. 5 as printed
    (un-normalised ``A^⊥ t``); each of the ``normalize_iterations`` that follow re-weights every
    pixel by ``1 / ‖A_i t‖²`` at the current direction and searches again, converging to the
    exact (Bruss–Horn) least-squares objective.

    Args:
        flow: ``(B, 2, H, W)`` flow from frame k to k+1, pixels.
        intrinsics: ``(B, 4)`` or ``(4,)`` pixels at the flow's resolution.
        valid: ``(B, H, W)`` usable pixels (None: all finite pixels).
        translation_norm: ``(B,)`` length given to the unit translation (module docstring).
        pixel_stride: use every n-th row and column.
        grid_size: directions of the exhaustive search on the half sphere.
        refine_steps: rounds of the pattern search after it.
        normalize_iterations: re-weighting rounds towards the normalised objective.
        robust: also multiply the weights by the Cauchy function of every pixel's residual,
            ``1 / (1 + (r / 2.385 σ)²)`` with ``σ = 1.4826 · median |r|`` (pixels), at each
            round: iteratively reweighted least squares that discounts outliers and moving
            objects.

    Returns:
        ``(t, ω)``, ``(B, 3)`` float64 each: the translation direction (scaled by
        ``translation_norm`` when given) and the rotation vector in radians.
    """
    flow, mask = _check_flow(flow, valid, intrinsics)
    batch, _, height, width = flow.shape
    K = _batch_intrinsics(intrinsics, batch)
    A_all, B_all = geometry.motion_matrices(K, height, width)
    sub = (slice(None, None, pixel_stride), slice(None, None, pixel_stride))
    grid = fibonacci_hemisphere(grid_size)
    t_out = torch.zeros(batch, 3, dtype=torch.float64)
    w_out = torch.zeros(batch, 3, dtype=torch.float64)
    for b in range(batch):
        keep = mask[b][sub].reshape(-1)
        if int(keep.sum()) < 6:  # fewer equations than unknowns: no estimate
            continue
        problem = _ContinuousProblem(
            A_all[b][sub].reshape(-1, 2, 3)[keep],
            B_all[b][sub].reshape(-1, 2, 3)[keep],
            flow[b][(slice(None), *sub)].reshape(2, -1).T[keep],
        )
        t, w = _search(problem, grid, refine_steps)
        weights = torch.ones_like(problem.q[:, 0])
        for _ in range(normalize_iterations):
            r, length2, _ = problem.residuals(t, w)
            # Pixels at the focus of expansion carry no information about t: the floor keeps
            # their weight finite.
            weights = 1.0 / length2.clamp_min(1e-6 * float(length2.median()) + 1e-18)
            if robust:
                sigma = (1.4826 * r.abs().median()).clamp_min(1e-6)
                weights = weights / (1.0 + (r / (2.385 * sigma)) ** 2)
            problem.set_weights(weights)
            t, w = _search(problem, grid, refine_steps)
        # t and −t fit equally well; the right one puts the (weighted) majority of points in
        # front of the camera, where ρ_i has the sign of A_i t · (v̂_i − B_i ω).
        _, length2, along = problem.residuals(t, w)
        if float((weights * length2 * torch.sign(along)).sum()) < 0:
            t = -t
        t_out[b], w_out[b] = t, w
    return _scaled(t_out, translation_norm), w_out
