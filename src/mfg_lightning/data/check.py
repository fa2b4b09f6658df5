"""Validate a dataset root before training.

``python -m mfg_lightning.data.check dataset=kitti dataset.data_root=/data/kitti/dataset``

Composes the same config as training (``conf/train.yaml`` with any overrides), builds the
dataset's train, val and test splits, and reports for each:

* sample counts (total and per sequence / world), native resolution and the input resolution;
* intrinsics (native and scaled to the input size);
* pose statistics from the ground truth of *every* sample: translation per sample (m), rotation
  angle (degrees);
* flow statistics (magnitude in input pixels, valid fraction; for Virtual KITTI also depth and
  moving-object fraction) from a few samples spread evenly over the split (``+check.samples=N``,
  default 4). For KITTI these few are the only pairs whose flow is computed (by DIS, and cached
  like in training) or read (``flow=files``, from ``flow.dir``); the report lists their ids;
* missing or unreadable files, listed, not fatal: every file every sample reads is checked
  cheaply (it exists; PNG/JPEG signature and end marker, which catches truncated downloads), and
  the sampled ones are decoded fully. Missing frames, short pose files and similar index
  problems are listed too (the datasets are built with ``skip_bad_samples=true``).

Human-readable lines come first; the LAST line of stdout is one JSON object with all figures.
Exit status: 0 when nothing is wrong, 1 when problems were listed, 2 when the root itself is
unusable (the error shows the expected layout). Nothing is written into ``data_root``.
"""

from __future__ import annotations

import inspect
import json
import logging
import math
import sys
import warnings
from typing import Any

import hydra
import numpy as np
import torch
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.core import geometry
from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.data_errors import DataFileError, DataRootError
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error
from mfg_lightning.flow import io as flow_io

log = logging.getLogger("mfg_lightning.data.check")

_SPLITS = ("train", "val", "test")


def _stats(values: torch.Tensor | np.ndarray) -> dict[str, float]:
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        return {"mean": math.nan, "max": math.nan}
    return {"mean": round(float(v.mean()), 6), "max": round(float(v.max()), 6)}


def pose_statistics(rel: torch.Tensor) -> dict[str, Any]:
    """Translation (m) and rotation angle (degrees) statistics of ``(N, 4, 4)`` relative poses."""
    rel = rel.double()
    t = rel[:, :3, 3]
    angle = torch.rad2deg(geometry.rotation_angle(rel[:, :3, :3]))
    return {
        "translation_m": _stats(t.norm(dim=-1)),
        "mean_translation_xyz_m": [round(float(x), 6) for x in t.mean(0)] if len(t) else [],
        "rotation_deg": _stats(angle),
        "finite": bool(torch.isfinite(rel).all()),
    }


def _flow_statistics(samples: list[dict[str, Any]]) -> dict[str, Any]:
    mags, valid_frac, out = [], [], {}
    for s in samples:
        mag = s["flow"].norm(dim=0)
        mags.append(mag[s["flow_valid"]].numpy())
        valid_frac.append(float(s["flow_valid"].float().mean()))
    out["magnitude_px"] = _stats(np.concatenate(mags) if mags else np.zeros(0))
    out["valid_fraction"] = round(float(np.mean(valid_frac)), 6) if valid_frac else math.nan
    if samples and "depth" in samples[0]:
        depth = torch.stack([s["depth"] for s in samples])
        known = depth[depth > 0]
        out["depth_m"] = (
            {"min": round(float(known.min()), 4), **_stats(known)} if known.numel() else {}
        )
    if samples and "object_mask" in samples[0]:
        out["object_fraction"] = round(
            float(np.mean([float(s["object_mask"].float().mean()) for s in samples])), 6
        )
    return out


def check_split(ds: Any, n_samples: int) -> tuple[dict[str, Any], list[str]]:
    """Figures and problems of one split's dataset."""
    problems: list[str] = []
    report: dict[str, Any] = {"samples": len(ds)}
    report["per_sequence"] = {k: len(v) for k, v in ds.sequences().items()}
    if hasattr(ds, "describe"):
        try:
            report["sequences"] = ds.describe()
        except DataFileError as err:
            problems.append(str(err))
    report["input_size"] = [ds.height, ds.width]
    report["pose"] = pose_statistics(ds.relative_poses())
    if hasattr(ds, "files"):
        seen: set[str] = set()
        for i in range(len(ds)):
            for path in ds.files(i):
                key = str(path)
                if key in seen:
                    continue
                seen.add(key)
                problem = flow_io.quick_check(path)
                if problem:
                    problems.append(problem)
        report["files_checked"] = len(seen)
    picks = sorted({round(x) for x in np.linspace(0, len(ds) - 1, num=min(n_samples, len(ds)))})
    loaded = []
    for i in picks:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                sample = ds[i]
            except DataFileError as err:
                sample = None
                problems.append(str(err))
        problems += [str(w.message) for w in caught if "skipping" in str(w.message)]
        if sample is not None:
            loaded.append(sample)
    report["flow_checked"] = [s["sample_id"] for s in loaded]
    report["flow"] = _flow_statistics(loaded)
    return report, problems


def check_dataset(dataset_cfg: DictConfig, n_samples: int = 4) -> dict[str, Any]:
    """Build every split of the configured dataset and report on it (see the module docstring).

    Raises:
        DataRootError: the root is missing or has the wrong layout.
    """
    target = dataset_cfg.get("_target_")
    kwargs: dict[str, Any] = {}
    if "skip_bad_samples" in inspect.signature(get_class(target)).parameters:
        kwargs["skip_bad_samples"] = True  # list bad files instead of stopping at the first
    datamodule = instantiate(dataset_cfg, **kwargs)
    report: dict[str, Any] = {
        "dataset": target,
        "data_root": dataset_cfg.get("data_root"),
        "input_size": [datamodule.height, datamodule.width],
        "splits": {},
        "problems": [],
    }
    for split in _SPLITS:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                ds = datamodule.build_dataset(split)
            except DataRootError:
                raise
            except (DataFileError, ValueError) as err:
                report["problems"].append(f"{split}: {err}")
                report["splits"][split] = {"samples": 0, "error": str(err)}
                continue
        report["problems"] += [f"{split}: {w.message}" for w in caught]
        split_report, problems = check_split(ds, n_samples)
        report["splits"][split] = split_report
        report["problems"] += [f"{split}: {p}" for p in problems]
        if split_report["samples"] == 0:
            report["problems"].append(f"{split}: no samples")
    report["ok"] = not report["problems"]
    return report


def _print_human(report: dict[str, Any]) -> None:
    print(f"dataset {report['dataset']} at {report['data_root']}, input {report['input_size']}")
    for split, r in report["splits"].items():
        if "error" in r:
            print(f"[{split}] ERROR {r['error']}")
            continue
        t, rot = r["pose"]["translation_m"], r["pose"]["rotation_deg"]
        mag = r["flow"]["magnitude_px"]
        print(
            f"[{split}] {r['samples']} samples {r['per_sequence']}; "
            f"|t| mean {t['mean']:.3f} m (max {t['max']:.3f}), "
            f"rotation mean {rot['mean']:.3f}° (max {rot['max']:.3f}); "
            f"|flow| mean {mag['mean']:.3f} px on {len(r['flow_checked'])} samples checked"
        )
        for seq, d in r.get("sequences", {}).items():
            h, w = d["native_size"]
            print(
                f"    {seq}: {d['frames']} frames, native {w}×{h}, "
                f"K native {d['intrinsics_native']} → input {d['intrinsics_input']}"
            )
    for p in report["problems"]:
        print(f"PROBLEM {p}")
    print("OK" if report["ok"] else f"{len(report['problems'])} problem(s) found")


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="check")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    n_samples = int(OmegaConf.select(cfg, "check.samples", default=4))
    try:
        report = check_dataset(cfg.dataset, n_samples)
    except DataRootError as err:
        # The JSON line stays the last line of stdout, for scripts; the error then exits 2.
        print(json.dumps({"dataset": cfg.dataset.get("_target_"), "ok": False, "error": str(err)}))
        raise
    _print_human(report)
    print(json.dumps(report, default=float))
    if not report["ok"]:
        sys.exit(1)  # problems were listed: not a user error of the command, a finding


if __name__ == "__main__":
    main()
