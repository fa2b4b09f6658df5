"""The stages of the reproduction study (``python -m mfg_lightning.reproduce``).

Each stage computes one JSON-able result, cached atomically as ``<results_dir>/<stage>.json``
(committed with the repository: a fresh clone resumes from them) and skipped when cached (an
interrupted study resumes). Models are trained by :func:`mfg_lightning.run.training.train` from
the ``train`` config composed with the study's overrides, into ``<work_dir>/models/<name>`` with
``resume=true`` (an interrupted training continues from its ``last.ckpt``) under the convergence
rule (``callbacks=convergence``, :mod:`mfg_lightning.run.convergence`, the study's
``convergence`` block) and the stage's caps (steps, time); checkpoints are selected on validation
(``val/ate``) only, never on the test sequences. Evaluation reuses
:mod:`mfg_lightning.analysis.scoring` (MFG at any k, classical baselines),
:mod:`mfg_lightning.analysis.basis`, :mod:`mfg_lightning.motion.object_motion` and its scores.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader, Subset

from mfg_lightning.core.atomic import atomic_write_text
from mfg_lightning.motion.baselines import VERSION as BASELINES_VERSION
from mfg_lightning.study.rules import growth

log = logging.getLogger("mfg_lightning.study")

Result = dict[str, Any]

#: The test samples of Table 1's * protocol: motions from each centre frame to ±1, ±2.
CENTRAL_OFFSETS = "dataset.offsets=[-2,-1,1,2]"


class Study:
    """The study's configuration, its work directory and its cached stage results.

    Args:
        cfg: the composed ``reproduce`` config.
        trainer_choice: the ``trainer`` group option every training run uses.
    """

    def __init__(self, cfg: DictConfig, trainer_choice: str = "default") -> None:
        self.cfg = cfg
        self.trainer_choice = trainer_choice
        self.work = Path(cfg.work_dir).expanduser()
        self.results = Path(cfg.results_dir).expanduser()
        self.ran: list[str] = []
        self.seconds: dict[str, float] = {}

    # -- cache ---------------------------------------------------------------------------

    def path(self, name: str) -> Path:
        return self.results / f"{name}.json"

    def cached(self, name: str) -> Result | None:
        try:
            return json.loads(self.path(name).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def stage(self, name: str, compute: Callable[[], Result | None]) -> Result | None:
        """The cached result of ``name``, else ``compute()`` (when the stage is selected and its
        inputs exist: it returns None otherwise), cached with the seconds it took."""
        done = self.cached(name)
        if done is not None:
            print(f"cached: {name}", flush=True)
            return done
        if name.split("/")[0] not in self.cfg.stages:
            return None
        start = time.perf_counter()
        result = compute()
        if result is None:
            return None
        result["seconds"] = time.perf_counter() - start
        result["commit"] = checkout_commit()
        # the classical methods' version: a later report tells a result that predates a fix of
        # theirs from the result itself, with or without git history
        result["baselines_version"] = BASELINES_VERSION
        atomic_write_text(self.path(name), json.dumps(result, indent=1) + "\n")
        self.ran.append(name)
        print(f"ran: {name} ({result['seconds']:.0f} s)", flush=True)
        return result

    # -- configs, data, models -----------------------------------------------------------

    def train_config(
        self, name: str, extra: list[str], steps: int, max_time: str | None = None
    ) -> DictConfig:
        """The ``train`` config of model ``name``: the study's data, the convergence rule with
        its caps (``steps``; ``max_time``, Lightning's "DD:HH:MM:SS"), then ``extra``."""
        from mfg_lightning.core.config import compose

        b = self.cfg.budget
        rule = [f"callbacks.convergence.{k}={v}" for k, v in self.cfg.convergence.items()]
        # a group choice in ``extra`` (flow=learned) replaces the data's own (flow=dis): Hydra
        # refuses two choices of one group
        chosen = {e.split("=", 1)[0] for e in extra if "=" in e and "." not in e.split("=")[0]}
        data = [d for d in self.cfg.data if str(d).split("=", 1)[0] not in chosen]
        ov = [
            *data,
            f"trainer={self.trainer_choice}",
            f"trainer.max_steps={int(steps)}",
            f"trainer.val_check_interval={max(1, min(int(b.val_every), int(steps)))}",
            "callbacks=convergence",
            "model.scheduler=null",
            *rule,
            "logger=csv",
            "~callbacks.rich_progress_bar",
            "++trainer.enable_progress_bar=false",
            "trainer.enable_model_summary=false",
            "model.image_log_every_n_steps=0",
            "test=false",
            "resume=true",
            f"seed={self.cfg.seed}",
            f"paths.output_dir={self.work / 'models' / name}",
            f"paths.cache_dir={self.cfg.paths.cache_dir}",
            *extra,
        ]
        if b.max_frames is not None:
            # before ``extra``, which may set its own (Table 2's smaller training set)
            ov.insert(len(data), f"dataset.max_frames={int(b.max_frames)}")
        if max_time:
            ov.append(f"++trainer.max_time={max_time}")
        return compose("train", ov)

    def datamodule(self, cfg: DictConfig, splits: tuple[str, ...] | None = None) -> Any:
        """The DataModule of the ``train`` config ``cfg`` with its missing flow computed: every
        split's (its ``prepare_data``), or only ``splits``' (a stage that reads no training pair
        renders none)."""
        from hydra.utils import instantiate

        if splits is None:
            dm = instantiate(cfg.dataset)
            dm.prepare_data()
            return dm
        # (image pairs have no flow to precompute: the end-to-end models' data)
        kw = {"precompute_flow": False} if "precompute_flow" in cfg.dataset else {}
        dm = instantiate(cfg.dataset, **kw)
        for split in splits:
            ds = dm.dataset(split)
            if hasattr(ds, "precompute_flow"):
                ds.precompute_flow(progress=False, workers=int(self.cfg.budget.workers))
        return dm

    def test_datamodule(self, extra: list[str]) -> Any:
        """A DataModule whose test split has Table 1's * samples (every centre frame to its
        :data:`CENTRAL_OFFSETS`, the +1 pairs giving †), whatever offsets the model trained
        on; only the test split's missing flow is computed."""
        cfg = self.train_config("main", [*extra, CENTRAL_OFFSETS], 1)
        return self.datamodule(cfg, splits=("test",))

    def train(self, name: str, extra: list[str], steps: int, max_time: str | None = None) -> Result:
        """Train (or resume) model ``name`` under the convergence rule, capped at ``steps`` and
        ``max_time``; its best checkpoint by ``val/ate`` (the last under an equal budget or a
        rule on another metric), the steps it ran, whether it converged and why, its curve."""
        from mfg_lightning.run.training import train

        cfg = self.train_config(name, extra, steps, max_time)
        out = Path(cfg.paths.output_dir)
        resumed = (out / "checkpoints" / "last.ckpt").is_file()
        start = time.perf_counter()
        train(cfg)
        seconds = time.perf_counter() - start
        rule = cfg.callbacks.convergence
        if rule.get("budget_steps") or rule.monitor != cfg.callbacks.model_checkpoint.monitor:
            # the schedule's end is the model, nothing is selected (the best checkpoints rank a
            # metric a rule on another one does not watch)
            why = "equal budget" if rule.get("budget_steps") else f"rule on {rule.monitor}"
            chosen, selected_on = out / "checkpoints" / "last.ckpt", f"last ({why})"
        else:
            chosen, selected_on = chosen_checkpoint(out)
        status = json.loads((out / "convergence.json").read_text())
        ran = int(status["step"] or 0)
        batch = int(cfg.dataset.batch_size)
        curve = logged_curve(out)
        for p in curve:
            p["samples"] = int(p["step"]) * batch
        from mfg_lightning.core.machine import cpu_kind

        # the precision the run trained in (``auto`` made concrete in its config.yaml) and the
        # CPU kind: seeds trained on different machines differ in both, and the report says so
        precision = str(OmegaConf.load(out / "config.yaml").trainer.get("precision", "32-true"))
        return {
            "name": name,
            "overrides": list(extra),
            "precision": precision,
            "cpu_kind": cpu_kind() if not torch.cuda.is_available() else "cuda",
            "steps": ran,
            "step_cap": int(steps),
            "time_cap": max_time,
            "batch_size": batch,
            "samples_seen": ran * batch,
            # the training's own time over every session (the callback's clock: a finished
            # model resumed here adds nothing), not this call's wall time
            "train_seconds": float(status.get("seconds") or seconds),
            "resumed": resumed,
            # relative to work_dir: the committed result names no path of this machine
            "checkpoint": str(chosen.relative_to(self.work)),
            "selected_on": selected_on,
            "recipe": recipe_of(cfg),
            "convergence": {k: v for k, v in status.items() if k != "curve"},
            "curve": curve,
        }

    def checkpoint(self, trained: Result) -> Path:
        """The checkpoint of a trained model's result (relative to ``work_dir``)."""
        return self.work / trained["checkpoint"]

    def model(self, trained: Result) -> Any:
        """The trained model of a stage result; a checkpoint that is not on this machine (a
        fresh clone resuming from the committed results) is rebuilt by training the model
        again with the same settings, and is then the one that is evaluated."""
        from mfg_lightning.run.checkpoints import module_from_checkpoint

        path = self.checkpoint(trained)
        if not path.is_file():
            log.warning("%s: not on this machine; training %s again", path, trained["name"])
            again = self.train(
                trained["name"], list(trained["overrides"]), trained["step_cap"],
                trained.get("time_cap"),
            )  # fmt: skip
            path = self.checkpoint(again)
        return module_from_checkpoint(str(path)).eval()

    def loader(self, dm: Any, split: str, forward_only: bool = False) -> DataLoader:
        """A split's evaluation loader; ``forward_only``: the samples ``k → k+1`` only."""
        from mfg_lightning.data.base import collate_samples

        ds = dm.dataset(split)
        if forward_only:
            # every dataset of the study lists its samples as (sequence, source, target)
            ds = Subset(ds, [i for i, (_, s, t) in enumerate(ds.samples) if t == s + 1])
        return DataLoader(
            ds, batch_size=int(self.cfg.budget.eval_batch_size), collate_fn=collate_samples
        )


def sparsity_variants(cfg: DictConfig) -> list[tuple[str, list[str], bool, float]]:
    """The runs of the sparsity sweep, in order: ``(name, overrides, plain, w_s)`` per
    ``sparsity.w_s``; for ``w_s = 100`` also one with ``sparsity.input_scale``, and for the
    largest ``w_s`` also one at ``sparsity.low_lr`` (to separate a collapse from the rate);
    ``plain`` is False for those two."""
    variants = []
    largest = max(float(w) for w in cfg.sparsity.w_s)
    for ws in cfg.sparsity.w_s:
        variants.append((f"ws{ws:g}", [f"model.loss.w_s={ws}"], True, ws))
        if float(ws) == 100.0:
            scale = cfg.sparsity.input_scale
            extra = [f"model.loss.w_s={ws}", f"model.net.input_scale={scale}"]
            variants.append((f"ws{ws:g}_scale{scale:g}", extra, False, ws))
        if float(ws) == largest and cfg.sparsity.get("low_lr"):
            lr = float(cfg.sparsity.low_lr)
            extra = [f"model.loss.w_s={ws}", f"model.optimizer.lr={lr:g}"]
            variants.append((f"ws{ws:g}_lr{lr:g}", extra, False, ws))
    return variants


def recipe_of(cfg: DictConfig) -> dict[str, Any]:
    """Batch, optimiser and schedule of a training config, as the report states them."""
    opt = cfg.model.optimizer
    sched = cfg.model.get("scheduler")
    return {
        "batch_size": int(cfg.dataset.batch_size),
        "optimizer": str(opt._target_).rsplit(".", 1)[-1],
        "lr": float(opt.lr),
        "betas": [float(b) for b in opt.get("betas", [])],
        "scheduler": None if not sched else str(sched._target_).rsplit(".", 1)[-1],
        "w_s": float(cfg.model.loss.w_s),
    }


# --------------------------------------------------------------------------------------------
# Evaluation helpers
# --------------------------------------------------------------------------------------------


def _seconds(max_time: str | None) -> float:
    """Lightning's ``max_time`` "DD:HH:MM:SS" in seconds (``inf``: no cap)."""
    if not max_time:
        return math.inf
    d, h, m, sec = (int(x) for x in str(max_time).split(":"))
    return float(((d * 24 + h) * 60 + m) * 60 + sec)


def main_run_serves(study: Study, main: dict | None, max_time: str | None = None) -> bool:
    """Whether the main model's run is the run a model of the main setting would make under
    the other models' caps: it met the rule (was not stopped by its own caps) within
    ``budget.other_steps`` and ``max_time`` (default ``budget.other_max_time``). Training
    such a model again gives the same model (the seed and data are the same; the sweep's
    w_s = 100 run repeated the main model's curve bit for bit), so it is not trained twice."""
    if main is None or not (main.get("convergence") or {}).get("converged"):
        return False
    b = study.cfg.budget
    cap = _seconds(max_time or b.get("other_max_time"))
    return int(main["steps"]) <= int(b.other_steps) and float(main["train_seconds"]) <= cap


def size_name(stride: int, seed: int | None) -> str:
    """The stage (and model) name of one point of the training-set-size curve."""
    return f"stride{stride}" + (f"_seed{seed}" if seed is not None else "")


def size_runs(cfg: DictConfig) -> list[tuple[int, int | None]]:
    """The size curve's (frame stride, extra seed or None) points: every stride at the study's
    seed, then the extra seeds at the smallest training set (the largest stride)."""
    strides = sorted({int(s) for s in cfg.size.strides}, reverse=True)
    runs: list[tuple[int, int | None]] = [(s, None) for s in strides]
    return runs + [(strides[0], int(seed)) for seed in cfg.size.seeds] if strides else runs


def mfg_scores(model: Any, loader: DataLoader, ks: list[float]) -> dict[str, dict[str, float]]:
    """The trajectory metrics of MFG at every k (``"1"``: all units) over one loader."""
    from mfg_lightning.analysis.scoring import Method, mfg_top_k_methods, score_methods

    predicts = mfg_top_k_methods(model, [float(k) for k in ks])
    rows = [Method(f"k={k:g}", p) for k, p in zip(ks, predicts, strict=True)]
    score_methods(rows, loader, warm_up=False)
    return {
        f"{k:g}": {key: float(v) for key, v in m.evaluator.compute().metrics.items()}
        for k, m in zip(ks, rows, strict=True)
    }


def active_fraction(model: Any, loader: DataLoader) -> float | None:
    """Mean fraction of hidden units active (> 0, before top-k) over a loader."""
    from mfg_lightning.analysis.basis import population_statistics

    return population_statistics(model.net, loader).summary()["active_fraction_mean"]


def chosen_checkpoint(run_dir: Path) -> tuple[Path, str]:
    """The checkpoint a study evaluates from a training run, and why: the best by ``val/ate``
    when some validation defined it, else ``last.ckpt``. (Validation on every Nth source frame,
    ``dataset.frame_stride`` > 1, has no five consecutive frames, so its frame-by-frame ATE is
    NaN at every validation: "best" would then be whichever checkpoint came first.)"""
    best = sorted((run_dir / "checkpoints").glob("best-*.ckpt"))
    last = run_dir / "checkpoints" / "last.ckpt"
    if not best:
        return last, "last (no validation)"
    if not any(math.isfinite(r.get("val/ate", math.nan)) for r in logged_curve(run_dir)):
        return last, "last (val/ate undefined at every validation)"
    return best[-1], "val/ate"


def logged_curve(run_dir: Path) -> list[dict[str, float]]:
    """The validation rows (``step``, ``val/*``) of a training run's CSV log, by step, across
    resumes (:func:`mfg_lightning.run.runs.read_csv_metrics`; a later row of a step wins)."""
    from mfg_lightning.run.runs import read_csv_metrics

    rows: dict[int, dict[str, float]] = {}
    for r in read_csv_metrics(run_dir / "csv"):
        if r.get("val/ate") not in (None, ""):
            vals = {k: float(v) for k, v in r.items() if k.startswith("val/") and v != ""}
            rows[int(r["step"])] = {"step": float(r["step"]), **vals}
    return [rows[s] for s in sorted(rows)]


def checkout_commit() -> str | None:
    from mfg_lightning.run.runs import git_commit

    c = git_commit()
    return c[:12] if c else None


def bin_errors(
    coverage: list[float], errors: list[float], edges: list[float]
) -> list[dict[str, float]]:
    """Mean error and count per coverage bin ``[edges[i], edges[i+1])`` (the last bin closed)."""
    cov = torch.tensor(coverage, dtype=torch.float64)
    err = torch.tensor(errors, dtype=torch.float64)
    out = []
    for i, (lo, hi) in enumerate(itertools.pairwise(edges)):
        last = i == len(edges) - 2
        sel = (cov >= lo) & ((cov <= hi) if last else (cov < hi))
        n = int(sel.sum())
        out.append({"lo": lo, "hi": hi, "n": n, "mean": float(err[sel].mean()) if n else None})
    return out


def coverage_bins(rows: list[Any], samples: list[tuple], edges: list[float]) -> dict[str, dict]:
    """Per scored method (``analysis.scoring.Method``), its +1 pairs' rotation and translation
    errors binned by the image fraction moving objects cover (``edges``), and the rotation
    error's growth over the bins; ``samples``: the test split's ``(sequence, source, target)``
    in the order the methods were scored."""
    forward = [t == s + 1 for _, s, t in samples]
    bins = {}
    for m in rows:
        pick = [i for i, f in enumerate(forward[: len(m.rot_err)]) if f]
        cov = [m.coverage[i] for i in pick]
        rot = bin_errors(cov, [m.rot_err[i] for i in pick], edges)
        bins[m.name] = {
            "rot_bins": rot,
            "trans_bins": bin_errors(cov, [m.trans_err[i] for i in pick], edges),
            "growth": growth(rot),
        }
    return bins


def object_motion_scores(
    model: Any, loader: DataLoader, cfg: Any, slow_px: float, flow_key: str = "flow"
) -> dict[str, dict[str, dict[str, float]]]:
    """Object-mask scores of the paper's filters and the threshold baseline, over all samples
    and split slow / fast by each sample's mean ground-truth object flow (near / far: the
    scores' own depth split). ``flow_key``: the batch's flow the model sees (``"flow"``, the
    estimated flow; ``"exact_flow"``, the rendered worlds' exact flow)."""
    from mfg_lightning.data.sample import model_inputs
    from mfg_lightning.metrics.object_motion import ObjectMotionScores
    from mfg_lightning.motion.object_motion import extract_object_motion, threshold_baseline

    groups = ("all", "slow", "fast")
    scores = {m: {g: ObjectMotionScores() for g in groups} for m in ("filters", "threshold")}
    for batch in loader:
        if batch is None or "object_mask" not in batch:
            continue
        flow, valid, _ = model_inputs(batch, flow_key)
        with torch.inference_mode():
            out = model(flow)
        depth, gt = batch["depth"], batch["object_mask"].bool()
        res = extract_object_motion(flow, out.v_t, out.v_omega, depth, cfg, valid=valid)
        base = threshold_baseline(res.residual, cfg.baseline_threshold, res.valid)
        speed = (batch["object_flow"].norm(dim=1) * gt).flatten(1).sum(1) / gt.flatten(1).sum(
            1
        ).clamp_min(1)
        sel = {"all": torch.ones_like(speed, dtype=torch.bool), "slow": speed < slow_px}
        sel["fast"] = ~sel["slow"]
        for name, mask, field in (
            ("filters", res.mask, res.object_flow),
            ("threshold", base, res.residual * base[:, None]),
        ):
            for g in groups:
                s = sel[g] & (gt.flatten(1).any(1) if g != "all" else sel[g])
                if s.any():
                    scores[name][g].update(
                        mask[s], field[s], gt[s], batch["object_flow"][s], depth[s], res.valid[s]
                    )
    return {
        m: {
            g: {k: float(v) for k, v in sc.compute().items()}
            for g, sc in by.items()
            if sc.update_count
        }
        for m, by in scores.items()
    }


def to_container(x: Any) -> Any:
    return OmegaConf.to_container(x, resolve=True) if OmegaConf.is_config(x) else x
