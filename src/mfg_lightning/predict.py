"""Run a trained model on sequences without ground truth.

``python -m mfg_lightning.predict ckpt_path=<file.ckpt> dataset=<name> [dataset.<key>=…]``

* KITTI odometry 11–21 (images and ``calib.txt``, no ``poses/``)::

      python -m mfg_lightning.predict ckpt_path=run/checkpoints/last.ckpt dataset=kitti \\
          dataset.data_root=/data/kitti/dataset 'dataset.test_sequences=[11,12]'

* one's own video, a folder of frames with the camera given in pixels
  (:mod:`mfg_lightning.data.image_folder`)::

      python -m mfg_lightning.predict ckpt_path=… dataset=image_folder \\
          dataset.data_root=/data/drive/frames dataset.fx=718.9 dataset.fy=718.9 \\
          dataset.cx=607.2 dataset.cy=185.2

A dataset with a ``predict`` split (KITTI: the test sequences, poses optional; the image folder)
is read through it; the others (synthetic, Virtual KITTI) through their test split, whose
ground truth is then simply not used. Flow comes from the dataset exactly as in training (KITTI
and the image folder: OpenCV's DIS, cached). The dataset's input size must be the network's.

Written into the run directory (``hydra.run.dir``):

* ``poses/kitti/<seq>.txt`` and ``poses/tum/<seq>.txt``: the trajectory ``T_world_cam`` of
  every frame, composed from the predicted motions (the first frame is the identity; see
  :func:`mfg_lightning.trajectory.trajectories.sequence_trajectory`), in the formats ``evo`` and
  the KITTI
  devkit read; TUM timestamps from the dataset (KITTI's ``times.txt``) or ``frame / frame_rate``;
* ``motions/<seq>.csv``: per frame pair, the predicted ``t`` (m) and ``ω`` (rad), camera ``k + 1``
  in camera ``k`` (x right, y down, z forward);
* ``masks/<seq>/<frame:06d>.png`` when the dataset delivers depth (synthetic, Virtual KITTI):
  the object mask of the paper's section 4 filters at the input size (255 = moving);
* ``trajectories/{trajectory,drift,error}_<seq>.png`` when the split has ground-truth poses
  (KITTI 00–10, synthetic, Virtual KITTI): the predicted trajectory over the true one, drift per
  segment length and position error, after ``predict.align`` (``none``, the default, as
  predicted; ``se3``, ``sim3``, ``scale``, ``scale_7dof``), which their titles name; and in
  ``predict.json`` the whole-trajectory metrics of the aligned trajectories (``ate_traj``, RPE,
  drift: :func:`mfg_lightning.metrics.aligned_trajectory_metrics`). The pose files are never
  aligned;
* ``predict.json``: what was written, per sequence.

An end-to-end checkpoint (``experiment=end_to_end``) holds its fine-tuned flow network too: with
``flow=learned`` and no ``flow.weights`` the dataset's flow is that network's (the flow its MFG
trained on), e.g. ``dataset=synthetic flow=learned``; another flow is used as given, with a
warning.

The prediction itself, its checks and its writers are :mod:`mfg_lightning.run.prediction`'s.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import lightning as L
from omegaconf import DictConfig, open_dict

from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import UserError, exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.run.checkpoints import peek_checkpoint, stored_model_config
from mfg_lightning.run.prediction import predict

log = logging.getLogger("mfg_lightning.predict")


def end_to_end_flow(cfg: DictConfig) -> None:
    """The flow of an end-to-end checkpoint's prediction: its own network under ``flow=learned``
    without ``flow.weights`` (set to the checkpoint); refused on ``dataset=image_pairs``, whose
    flow is the exact flow (the network runs inside the training module only)."""
    path = Path(str(cfg.ckpt_path)).expanduser()
    if not path.is_file():
        return  # (predict names the missing file)
    ckpt = peek_checkpoint(path)
    if "flow_net_config" not in ckpt or stored_model_config(ckpt) is None:
        return  # an MFG checkpoint (or not a checkpoint: predict says so)
    if str(cfg.dataset.get("_target_", "")).endswith("ImagePairsDataModule"):
        raise UserError(
            f"{path} was trained end to end: predict its poses on frames whose flow its own "
            "network estimates, e.g. dataset=synthetic flow=learned (dataset=image_pairs "
            "carries the exact flow)"
        )
    flow = cfg.get("flow") or {}
    if flow.get("source") == "learned" and not flow.get("weights"):
        with open_dict(cfg):
            cfg.flow.weights = str(path)
        log.info("flow=learned: the flow network of the end-to-end checkpoint %s", path)
    elif flow.get("source") != "learned" or Path(str(flow.get("weights"))) != path:
        log.warning(
            "%s was trained end to end on its own flow network's flow; this prediction reads "
            "flow=%s (flow=learned without flow.weights reads the checkpoint's)",
            path,
            flow.get("source"),
        )


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="predict")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    end_to_end_flow(cfg)
    written = predict(cfg)
    for seq, files in written.items():
        print(f"{seq}: {files['frames']} poses in {files['kitti']} and {files['tum']}")


if __name__ == "__main__":
    main()
