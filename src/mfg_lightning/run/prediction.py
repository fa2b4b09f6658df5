"""Poses for sequences without ground truth: what ``python -m mfg_lightning.predict`` runs (its
docstring lists the files it writes).

:class:`MotionPredictor` puts a trained :class:`~mfg_lightning.models.mfg_module.MFGLitModule`
into Lightning's predict loop; :func:`gather` groups its batch outputs into one
:class:`PredictedSequence` per sequence and checks that the pairs chain; :func:`write_sequence`
writes a sequence's pose files (KITTI, TUM), its motions CSV and its object masks;
:func:`end_to_end_flow` gives an end-to-end checkpoint its own flow network;
:func:`score_against_ground_truth` draws and scores the sequences where the split has ground
truth; :func:`predict` does all of it for a composed ``predict`` config.
"""

from __future__ import annotations

import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from lightning.pytorch.utilities.model_helpers import is_overridden
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from mfg_lightning.core import geometry
from mfg_lightning.core.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.core.errors import UserError
from mfg_lightning.core.tables import finite_or_none
from mfg_lightning.data.sample import model_inputs
from mfg_lightning.metrics.alignment import configured_align
from mfg_lightning.metrics.ate_traj import aligned_trajectory_metrics
from mfg_lightning.models.mfg import validate_top_k
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.motion.object_motion import ObjectMotionConfig, extract_object_motion
from mfg_lightning.pictures import plots
from mfg_lightning.run.checkpoints import (
    module_from_checkpoint,
    peek_checkpoint,
    stored_model_config,
)
from mfg_lightning.run.runs import run_info
from mfg_lightning.trajectory import trajectories
from mfg_lightning.trajectory.pose_io import frame_times, write_trajectory

log = logging.getLogger("mfg_lightning.predict")

#: the columns of ``motions/<seq>.csv``
MOTION_COLUMNS = ("frame", "target", "time_s", "t_x_m", "t_y_m", "t_z_m",
                  "omega_x_rad", "omega_y_rad", "omega_z_rad")  # fmt: skip


class PredictionError(UserError):
    """The predictions cannot form a trajectory (a frame pair is missing)."""


class MotionPredictor(L.LightningModule):
    """Lightning's predict loop around a trained :class:`MFGLitModule`.

    Per batch: the egomotion ``(t, ω)`` in closed form from the predicted fields and, when the
    batch carries depth and ``object_motion`` is set, the object masks of the paper's filters.
    """

    def __init__(self, module: MFGLitModule, object_motion: ObjectMotionConfig | None) -> None:
        super().__init__()
        self.module = module
        self.object_motion = object_motion

    def predict_step(self, batch: dict[str, Any] | None, batch_idx: int) -> dict[str, Any] | None:
        """Returns ``sequence`` (B names), ``frame``, ``target`` ``(B,)``, ``t``, ``omega``
        ``(B, 3)`` float64 on the CPU, ``mask`` ``(B, H, W)`` bool with depth and ``pose``
        ``(B, 4, 4)`` float64, the true ``T_src,tgt``, where the split has ground truth."""
        if batch is None:  # every sample of the batch was skipped as unreadable
            return None
        flow, valid, _ = model_inputs(batch)
        t, w, out = self.module.predict_motion(flow, batch["intrinsics"])
        result = {
            "sequence": list(batch["sequence"]),
            "frame": batch["frame"].cpu(),
            "target": batch["target"].cpu(),
            "t": t.double().cpu(),
            "omega": w.double().cpu(),
        }
        if "pose" in batch:  # the split's ground truth: figures and metrics, never the poses
            result["pose"] = batch["pose"].double().cpu()
        if self.object_motion is not None and "depth" in batch:
            res = extract_object_motion(
                flow, out.v_t, out.v_omega, batch["depth"], self.object_motion, valid=valid
            )
            result["mask"] = res.mask.cpu()
        return result


@dataclass
class PredictedSequence:
    """The predictions of one sequence, in frame order.

    Attributes:
        frames: ``(N − 1,)`` source frames k (consecutive), each predicted for ``k → k + 1``.
        t, omega: ``(N − 1, 3)`` float64 translation (m) and rotation (rad) per pair.
        masks: ``(N − 1, H, W)`` bool object masks, or None without depth.
    """

    frames: np.ndarray
    t: Tensor
    omega: Tensor
    masks: Tensor | None

    def trajectory(self) -> Tensor:
        """``(N, 4, 4)`` float64 camera-to-world poses, frame ``frames[0]`` at the identity."""
        return trajectories.sequence_trajectory(geometry.motion_to_pose(self.t, self.omega))


def gather(outputs: list[dict[str, Any] | None]) -> dict[str, PredictedSequence]:
    """The batch outputs of :class:`MotionPredictor` grouped by sequence, sorted by frame.

    Raises:
        PredictionError: a sequence whose pairs are not ``k → k + 1`` for consecutive k (a
            frame could not be read, or a dataset split with other offsets).
    """
    kept = [o for o in outputs if o is not None]
    if not kept:
        raise PredictionError("no predictions: every sample was skipped")
    names = [s for o in kept for s in o["sequence"]]
    frame = torch.cat([o["frame"] for o in kept]).numpy()
    target = torch.cat([o["target"] for o in kept]).numpy()
    t, w = torch.cat([o["t"] for o in kept]), torch.cat([o["omega"] for o in kept])
    has_masks = all("mask" in o for o in kept)
    masks = torch.cat([o["mask"] for o in kept]) if has_masks else None
    result: dict[str, PredictedSequence] = {}
    for seq in dict.fromkeys(names):
        rows = np.array([i for i, s in enumerate(names) if s == seq])
        rows = rows[np.argsort(frame[rows], kind="stable")]
        f, g = frame[rows], target[rows]
        other = np.flatnonzero(g != f + 1)
        if other.size:
            k = other[0]
            raise PredictionError(
                f"sequence {seq}: a pair {f[k]} → {g[k]}; a trajectory composes the pairs "
                "k → k + 1 only (set the dataset's offsets to [1])"
            )
        jumps = np.flatnonzero(np.diff(f) != 1)
        if jumps.size:
            k = jumps[0]
            raise PredictionError(
                f"sequence {seq}: no prediction from frame {f[k] + 1} to {f[k + 1]} (a missing "
                "or unreadable image?); a trajectory needs every pair k → k + 1"
            )
        index = torch.from_numpy(rows)
        result[seq] = PredictedSequence(
            f, t[index], w[index], None if masks is None else masks[index]
        )
    return result


def true_trajectories(
    outputs: list[dict[str, Any] | None], frames: dict[str, np.ndarray]
) -> dict[str, Tensor]:
    """The ground-truth trajectory of every predicted sequence, where every sample had a pose.

    Args:
        outputs: the batch outputs of :class:`MotionPredictor`.
        frames: sequence → its ``(N − 1,)`` consecutive source frames (as :func:`gather` sorted
            them).

    Returns:
        Sequence → ``(N, 4, 4)`` float64 poses composed from the true motions ``k → k + 1``
        (frame ``frames[0]`` at the identity, as the prediction); empty without ground truth.
    """
    kept = [o for o in outputs if o is not None]
    if not kept or not all("pose" in o for o in kept):
        return {}
    motion = {
        (seq, int(f)): pose
        for o in kept
        for seq, f, pose in zip(o["sequence"], o["frame"], o["pose"], strict=True)
    }
    return {
        seq: trajectories.sequence_trajectory(torch.stack([motion[(seq, int(f))] for f in fs]))
        for seq, fs in frames.items()
    }


def _mask_png(mask: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    if not ok:
        raise OSError("OpenCV could not encode a mask as PNG")
    return data.tobytes()


def write_sequence(
    out: Path, seq: str, pred: PredictedSequence, times: np.ndarray
) -> dict[str, Any]:
    """Write one sequence's trajectory (KITTI, TUM), motions CSV and masks; what was written.

    Args:
        out: the run directory.
        seq: the sequence name.
        pred: its predictions (N − 1 pairs).
        times: ``(N,)`` seconds of frames ``frames[0] … frames[-1] + 1``.
    """
    poses = pred.trajectory().numpy()
    kitti, tum = write_trajectory(out, seq, times, poses)
    table = np.column_stack(
        [pred.frames, pred.frames + 1, times[:-1], pred.t.numpy(), pred.omega.numpy()]
    )
    buf = io.StringIO()
    fmt = ["%d", "%d"] + ["%.9g"] * 7  # float32 predictions: 9 digits are exact
    np.savetxt(buf, table, fmt=fmt, delimiter=",", header=",".join(MOTION_COLUMNS), comments="")
    motions = out / "motions" / f"{seq}.csv"
    atomic_write_text(motions, buf.getvalue())
    written: dict[str, Any] = {
        "frames": len(poses),
        "first_frame": int(pred.frames[0]),
        "kitti": str(kitti),
        "tum": str(tum),
        "motions": str(motions),
    }
    if pred.masks is not None:
        mask_dir = out / "masks" / seq
        for frame, mask in zip(pred.frames, pred.masks.numpy(), strict=True):
            atomic_write_bytes(mask_dir / f"{frame:06d}.png", _mask_png(mask))
        written["masks"] = str(mask_dir)
    return written


def predict_align(cfg: DictConfig) -> str:
    """``predict.align``, checked (``none`` when the config has none)."""
    return configured_align(cfg.predict.get("align"), "predict.align")


def score_against_ground_truth(
    cfg: DictConfig, outputs: list[dict[str, Any] | None], sequences: dict[str, Any]
) -> dict[str, Any]:
    """Where the split has ground truth: draw each sequence's figures after ``predict.align``
    and return the whole-trajectory metrics of the aligned trajectories (``predict.json``'s
    ``align`` and ``metrics``); nothing without ground truth."""
    align = predict_align(cfg)
    truth = true_trajectories(outputs, {seq: p.frames for seq, p in sequences.items()})
    if not truth:
        return {}
    pairs = {seq: (p.trajectory(), truth[seq]) for seq, p in sequences.items()}
    out = Path(cfg.paths.output_dir) / "trajectories"
    plots.write_trajectory_figures(pairs, out, align=align)
    metrics = aligned_trajectory_metrics(pairs, align)
    return {"align": align, "metrics": {k: finite_or_none(v) for k, v in metrics.items()}}


def end_to_end_flow(cfg: DictConfig) -> dict[str, Any] | None:
    """The flow config of an end-to-end checkpoint's prediction, or None to read ``cfg.flow`` as
    given: under ``flow=learned`` without ``flow.weights``, the checkpoint's own flow network.
    Refused on ``dataset=image_pairs``, whose flow is the exact flow (the network runs inside the
    training module only). The config itself is not changed."""
    path = Path(str(cfg.ckpt_path)).expanduser()
    if not path.is_file():
        return None  # (predict names the missing file)
    ckpt = peek_checkpoint(path)
    if "flow_net_config" not in ckpt or stored_model_config(ckpt) is None:
        return None  # an MFG checkpoint (or not a checkpoint: predict says so)
    if str(cfg.dataset.get("_target_", "")).endswith("ImagePairsDataModule"):
        raise UserError(
            f"{path} was trained end to end: predict its poses on frames whose flow its own "
            "network estimates, e.g. dataset=synthetic flow=learned (dataset=image_pairs "
            "carries the exact flow)"
        )
    flow = cfg.get("flow") or {}
    if flow.get("source") == "learned" and not flow.get("weights"):
        log.info("flow=learned: the flow network of the end-to-end checkpoint %s", path)
        return {**OmegaConf.to_container(flow, resolve=True), "weights": str(path)}
    if flow.get("source") != "learned" or Path(str(flow.get("weights"))) != path:
        log.warning(
            "%s was trained end to end on its own flow network's flow; this prediction reads "
            "flow=%s (flow=learned without flow.weights reads the checkpoint's)",
            path,
            flow.get("source"),
        )
    return None


def predict(cfg: DictConfig) -> dict[str, dict[str, Any]]:
    """Predict every sequence of the configured dataset and write the files
    (:mod:`mfg_lightning.predict` lists them) and ``predict.json``.

    A dataset with a ``predict`` split is read through it, the others through their test split.

    Returns:
        Per sequence, what was written (``predict.json``'s ``sequences``).
    """
    out = Path(cfg.paths.output_dir)
    predict_align(cfg)  # a wrong value is an error before anything is predicted
    module = module_from_checkpoint(cfg.ckpt_path, top_k=validate_top_k(cfg.model.top_k))
    flow = end_to_end_flow(cfg)
    datamodule = instantiate(cfg.dataset) if flow is None else instantiate(cfg.dataset, flow=flow)
    net_hw = (module.net.height, module.net.width)
    if (datamodule.height, datamodule.width) != net_hw:
        raise ValueError(
            f"dataset.height×width is {datamodule.height}×{datamodule.width} but the network of "
            f"{cfg.ckpt_path} takes {net_hw[0]}×{net_hw[1]}: pass dataset.height={net_hw[0]} "
            f"dataset.width={net_hw[1]}"
        )
    has_predict = is_overridden("predict_dataloader", datamodule, L.LightningDataModule)
    split = "predict" if has_predict else "test"
    loader = datamodule.predict_dataloader() if has_predict else datamodule.test_dataloader()
    object_motion = instantiate(cfg.object_motion) if cfg.predict.object_masks else None
    trainer: L.Trainer = instantiate(
        cfg.trainer, logger=False, callbacks=[], enable_checkpointing=False
    )
    outputs = trainer.predict(MotionPredictor(module, object_motion), dataloaders=loader)
    # Everything is predicted and checked before the first file is written.
    sequences = gather(outputs)
    dataset = datamodule.dataset(split)
    written = {}
    for seq, pred in sequences.items():
        frames = np.append(pred.frames, pred.frames[-1] + 1)
        times = frame_times(dataset, seq, frames, float(cfg.predict.frame_rate))
        written[seq] = write_sequence(out, seq, pred, times)
        log.info("%s: %d poses → %s", seq, written[seq]["frames"], written[seq]["kitti"])
    summary = {
        "ckpt_path": str(cfg.ckpt_path),
        "dataset": cfg.dataset.get("_target_"),
        "split": split,
        "sequences": written,
        **score_against_ground_truth(cfg, outputs, sequences),
        **run_info(),
    }
    atomic_write_text(out / "predict.json", json.dumps(summary, indent=2) + "\n")
    return written
