"""Evaluate a checkpoint.

``python -m mfg_lightning.evaluate ckpt_path=… [dataset=…] [model.top_k=…]``

``task=egomotion`` (default) runs the test split and writes, into the run directory:

* ``metrics.json``: every ``test/*`` metric (ATE over 5-frame snippets, RPE, drift, per-frame
  errors, per sequence under ``test/<seq>/…``);
* ``sequences.md`` / ``sequences.csv``: one row per test sequence;
* ``poses/kitti/<seq>.txt`` and ``poses/tum/<seq>.txt`` (predicted) with ``<seq>_gt.txt`` beside
  them, readable unchanged by ``evo`` and KITTI's devkit;
* ``trajectories/{trajectory,drift,error}_<seq>.png`` (x–z over the ground truth, drift per segment
  length, error along the trajectory; :mod:`mfg_lightning.plots`), also TensorBoard images;
* with ``eval.top_k_sweep=[...]``: ``top_k.md`` / ``top_k.csv`` (the paper's Table 1 layout: one
  row per k, ATE mean ± std per sequence) and ``top_k.png`` (error against k %, supplementary
  Figure 4).

``task=object_motion`` scores the object masks and fields of the paper's section 4 against the
dataset's ground truth, with the plain-threshold baseline beside them (``object_motion.md``), and
draws picture grids in the paper's Figure 1 layout (``pictures/*.png`` and TensorBoard).
"""

from __future__ import annotations

import csv
import io
import logging
import math
from pathlib import Path
from typing import Any

import hydra
import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.atomic import atomic_write_bytes, atomic_write_text
from mfg_lightning.checkpoints import module_from_checkpoint
from mfg_lightning.config import CONFIG_DIR
from mfg_lightning.metrics.evaluator import EvaluationResult
from mfg_lightning.models.mfg import validate_top_k
from mfg_lightning.models.mfg_module import MFGLitModule
from mfg_lightning.runs import exit_on_user_error, run_info, to_float, write_metrics

log = logging.getLogger("mfg_lightning.evaluate")


def _fmt(x: float | None, digits: int = 4) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pm(metrics: dict[str, Any], key: str) -> str:
    """``mean ± std`` of ``key`` and ``key_std``."""
    mean, std = to_float(metrics.get(key)), to_float(metrics.get(f"{key}_std"))
    return "–" if mean is None else f"{mean:.4f} ± {_fmt(std)}"


def _scoped(metrics: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The metrics under ``prefix`` with the prefix removed (``test/09/ate`` → ``ate``)."""
    return {k[len(prefix) :]: v for k, v in metrics.items() if k.startswith(prefix)}


def _table(header: list[str], rows: list[list[str]]) -> tuple[str, str]:
    """The same table as Markdown and as CSV."""
    md = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    md += ["| " + " | ".join(r) + " |" for r in rows]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return "\n".join(md) + "\n", buf.getvalue()


def sequence_table(metrics: dict[str, Any], sequences: list[str]) -> tuple[str, str]:
    """Per-sequence table: ATE (mean ± std, m), RPE translation (m) and rotation (rad), drift."""
    header = ["sequence", "ATE (m)", "ATE RMSE (m)", "RPE trans (m)", "RPE rot (rad)",
              "drift t (%)", "drift r (deg/100m)"]  # fmt: skip
    rows = []
    for name, prefix in [(s, f"test/{s}/") for s in sequences] + [("all", "test/")]:
        m = _scoped(metrics, prefix)
        rows.append(
            [
                name,
                _pm(m, "ate"),
                _fmt(to_float(m.get("ate_rmse"))),
                _fmt(to_float(m.get("rpe_trans"))),
                _fmt(to_float(m.get("rpe_rot")), 5),
                _fmt(to_float(m.get("drift_t_err")), 2),
                _fmt(to_float(m.get("drift_r_err")), 2),
            ]
        )
    return _table(header, rows)


def top_k_table(results: dict[float, dict[str, Any]], sequences: list[str]) -> tuple[str, str]:
    """Table 1's layout: one row per k (%), ATE mean ± std per sequence, then RPE."""
    header = ["k (%)", *[f"ATE {s}" for s in sequences], "ATE all", "RPE trans (m)",
              "RPE rot (rad)"]  # fmt: skip
    rows = []
    for k, m in sorted(results.items(), reverse=True):
        per = [_pm(_scoped(m, f"test/{s}/"), "ate") for s in sequences]
        overall = _scoped(m, "test/")
        rows.append(
            [
                f"{100 * k:g}",
                *per,
                _pm(overall, "ate"),
                _fmt(to_float(overall.get("rpe_trans"))),
                _fmt(to_float(overall.get("rpe_rot")), 5),
            ]
        )
    return _table(header, rows)


def top_k_plot(results: dict[float, dict[str, Any]], sequences: list[str]) -> bytes:
    """ATE against k % (log axis), one line per sequence: the supplementary Figure 4."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = sorted(results)
    fig, ax = plt.subplots(figsize=(5.5, 3.5), dpi=120)
    for s in [*sequences, None]:
        key = f"test/{s}/ate" if s else "test/ate"
        std_key = f"test/{s}/ate_std" if s else "test/ate_std"
        y = [to_float(results[k].get(key)) for k in ks]
        e = [to_float(results[k].get(std_key)) or 0.0 for k in ks]
        if all(v is None for v in y):
            continue
        y = [float("nan") if v is None else v for v in y]
        ax.errorbar(
            [100 * k for k in ks], y, yerr=e, marker="o", capsize=3,
            label=f"sequence {s}" if s else "all", linestyle="-" if s else "--",
        )  # fmt: skip
    ax.set_xscale("log")
    ax.set_xlabel("hidden units kept, k (%)")
    ax.set_ylabel("ATE over 5-frame snippets (m)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def build(cfg: DictConfig) -> tuple[MFGLitModule, L.LightningDataModule, L.Trainer]:
    """The model from the checkpoint, the dataset (given, or the checkpoint's) and a Trainer."""
    top_k = validate_top_k(cfg.model.get("top_k"))
    model = module_from_checkpoint(cfg.ckpt_path, top_k=top_k)
    if cfg.get("dataset") is not None:
        dataset_cfg = cfg.dataset
    elif model.dataset_config is not None:
        dataset_cfg = OmegaConf.create(model.dataset_config)
    else:
        raise ValueError(
            f"{cfg.ckpt_path} stores no dataset config and has no run directory config.yaml "
            "beside it: pass dataset=<name>"
        )
    dataset_cfg = OmegaConf.merge(dataset_cfg, {"eval_batch_size": cfg.eval.batch_size})
    datamodule = instantiate(dataset_cfg)
    out = Path(cfg.paths.output_dir)
    logger = L.pytorch.loggers.TensorBoardLogger(
        str(out), name="tensorboard", version="", default_hp_metric=False
    )
    trainer = L.Trainer(
        accelerator=cfg.eval.accelerator, devices=1, logger=logger,
        enable_checkpointing=False, enable_model_summary=False,
    )  # fmt: skip
    return model, datamodule, trainer


def write_trajectories(evaluation: EvaluationResult, out: Path, frame_rate: float) -> list[Path]:
    """Predicted and ground-truth trajectories of one test run, KITTI and TUM formats."""
    from mfg_lightning.pose_io import write_kitti_poses, write_tum_poses

    written = []
    for seq, sp in evaluation.sequences.items():
        times = sp.frames.double().numpy() / frame_rate
        for suffix, poses in (("", sp.pred), ("_gt", sp.gt)):
            kitti = out / "poses" / "kitti" / f"{seq}{suffix}.txt"
            tum = out / "poses" / "tum" / f"{seq}{suffix}.txt"
            write_kitti_poses(kitti, poses.numpy())
            write_tum_poses(tum, times, poses.numpy())
            written += [kitti, tum]
    return written


def evaluate_egomotion(cfg: DictConfig) -> dict[str, Any]:
    model, datamodule, trainer = build(cfg)
    out = Path(cfg.paths.output_dir)
    sweep = list(cfg.eval.top_k_sweep) if cfg.eval.get("top_k_sweep") else [model.net.top_k]
    results: dict[float, dict[str, Any]] = {}
    evaluations: dict[float, EvaluationResult | None] = {}
    for k in sweep:
        model.net.top_k = validate_top_k(k)
        trainer.test(model, datamodule=datamodule, verbose=len(sweep) == 1)
        key = 1.0 if k is None else float(k)
        results[key] = {
            name: to_float(v)
            for name, v in trainer.callback_metrics.items()
            if name.startswith("test/")
        }
        evaluations[key] = model.last_evaluation.get("test")
        log.info("top_k=%s: ATE %s", k, _pm(_scoped(results[key], "test/"), "ate"))
    # Everything is computed; only now are files written (each atomically). metrics.json, the
    # sequence table and the pose files all describe the full model (k = 1) when the sweep has
    # it, else its largest k: never whichever k happened to run last.
    final_k = 1.0 if 1.0 in results else max(results)
    final, evaluation = results[final_k], evaluations[final_k]
    sequences = sorted(evaluation.sequences) if evaluation else []
    if cfg.eval.write_poses and evaluation is not None and sequences:
        write_trajectories(evaluation, out, cfg.eval.frame_rate)
    if evaluation is not None and sequences:
        from mfg_lightning.plots import write_trajectory_figures

        write_trajectory_figures(
            {s: (evaluation.sequences[s].pred, evaluation.sequences[s].gt) for s in sequences},
            out / "trajectories",
            trainer.logger.experiment if trainer.logger is not None else None,
        )
    md, csv_text = sequence_table(final, sequences)
    atomic_write_text(out / "sequences.md", md)
    atomic_write_text(out / "sequences.csv", csv_text)
    extra: dict[str, Any] = {"ckpt_path": str(cfg.ckpt_path), "task": "egomotion", **run_info()}
    if len(results) > 1:
        md, csv_text = top_k_table(results, sequences)
        atomic_write_text(out / "top_k.md", md)
        atomic_write_text(out / "top_k.csv", csv_text)
        atomic_write_bytes(out / "top_k.png", top_k_plot(results, sequences))
        extra["top_k_sweep"] = {f"{k:g}": m for k, m in sorted(results.items(), reverse=True)}
    print(md)
    write_metrics(out / "metrics.json", final, extra)
    return final


def evaluate_object_motion(cfg: DictConfig) -> dict[str, Any]:
    from mfg_lightning.object_motion import extract_object_motion
    from mfg_lightning.object_motion_viz import object_motion_grid_batch, save_png

    model, datamodule, trainer = build(cfg)
    model.object_motion = instantiate(cfg.object_motion)
    out = Path(cfg.paths.output_dir)
    datamodule.setup("test")
    sample = datamodule.dataset("test")[0]
    if "depth" not in sample or "object_mask" not in sample:
        from mfg_lightning.object_motion import ObjectMotionError, _missing_depth_message

        raise ObjectMotionError(_missing_depth_message())
    trainer.test(model, datamodule=datamodule, verbose=False)
    metrics = {k: to_float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")}
    header = ["method", "IoU", "precision", "recall", "EPE (px)", "near IoU", "far IoU",
              "near recall", "far recall"]  # fmt: skip
    columns = ("iou", "precision", "recall", "epe", "near/iou", "far/iou", "near/recall",
               "far/recall")  # fmt: skip
    methods = (
        ("MFG + filters (paper §4)", "object"),
        ("‖r‖ threshold baseline", "object_baseline"),
    )
    rows = [
        [name] + [_fmt(metrics.get(f"test/{key}/{c}"), 3) for c in columns] for name, key in methods
    ]
    md, csv_text = _table(header, rows)
    # Pictures: the first batch's samples in the paper's Figure 1 layout.
    import torch

    loader = datamodule.test_dataloader()
    batch = next(iter(loader))
    n = int(cfg.eval.num_pictures)
    model.eval()
    flow = batch["flow"][:n]
    with torch.no_grad():
        pred = model(flow)
        res = extract_object_motion(
            flow, pred.v_t, pred.v_omega, batch["depth"][:n], model.object_motion,
            valid=batch["flow_valid"][:n],
        )  # fmt: skip
    grid = object_motion_grid_batch(
        res, flow, rgb=batch["rgb"][:n] if "rgb" in batch else None, depth=batch["depth"][:n],
        gt_mask=batch["object_mask"][:n], max_samples=n, headers=list(batch["sample_id"][:n]),
    )  # fmt: skip
    atomic_write_text(out / "object_motion.md", md)
    atomic_write_text(out / "object_motion.csv", csv_text)
    save_png(grid, out / "pictures" / "object_motion.png")
    trainer.logger.experiment.add_image("test/object_motion", grid, 0, dataformats="HWC")
    extra = {"ckpt_path": str(cfg.ckpt_path), "task": "object_motion", **run_info()}
    write_metrics(out / "metrics.json", metrics, extra)
    print(md)
    return metrics


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="evaluate")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    L.seed_everything(cfg.seed, workers=True)
    if cfg.task == "egomotion":
        evaluate_egomotion(cfg)
    elif cfg.task == "object_motion":
        evaluate_object_motion(cfg)
    else:
        raise ValueError(f"task must be 'egomotion' or 'object_motion', got {cfg.task!r}")


if __name__ == "__main__":
    main()
