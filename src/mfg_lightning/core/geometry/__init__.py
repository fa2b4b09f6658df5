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

The module is a package of three parts with one import for its callers
(``from mfg_lightning.core import geometry``): :mod:`.fields` (grids, A and B, fields, recovery,
reprojection), :mod:`.se3` (rotations, poses, egomotion) and :mod:`.precision` (float32 inside
autocast).
"""

from mfg_lightning.core.geometry.fields import (
    FieldBasis,
    backproject,
    field_basis,
    motion_field,
    motion_matrices,
    normalized_grid,
    project,
    recover_motion,
    reprojection_flow,
    rotational_field,
    scale_intrinsics,
    translational_field,
)
from mfg_lightning.core.geometry.precision import (
    autocast_devices,
    float32_math,
    full_precision,
    to_float32,
)
from mfg_lightning.core.geometry.se3 import (
    invert_pose,
    motion_to_pose,
    pose_to_motion,
    project_to_se3,
    relative_pose,
    rotation_angle,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    trajectory_from_motions,
)

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
    "project_to_se3",
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
