"""The stages of the reproduction study (``python -m mfg_lightning.reproduce``).

Each stage computes one JSON-able result, cached atomically as ``<results_dir>/<stage>.json``
(a new results folder starts from the committed ones, ``start_from``: a fresh clone resumes from
them) and skipped when cached (an interrupted study resumes). Models are trained by
:func:`mfg_lightning.run.training.train` from the ``train`` config composed once per model with
the study's overrides and its settings as numbers, into ``<work_dir>/models/<name>`` with
``resume=true`` (an interrupted training continues from its ``last.ckpt``) under the convergence
rule (``callbacks=convergence``, :mod:`mfg_lightning.run.convergence`, the study's
``convergence`` block) and the stage's caps (steps, time); checkpoints are selected on validation
(``val/ate``) only, never on the test sequences. Evaluation reuses
:mod:`mfg_lightning.analysis.scoring` (MFG at any k, classical baselines),
:mod:`mfg_lightning.analysis.basis`, :mod:`mfg_lightning.motion.object_motion` and its scores.
"""

from __future__ import annotations

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
from mfg_lightning.core.paths import portable_path
from mfg_lightning.motion.baselines import VERSION as BASELINES_VERSION

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
        # each model's training config, composed once (its data, its datamodule's and its
        # evaluation's, all read from it)
        self._configs: dict[tuple, DictConfig] = {}

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
        if not self.cfg.poses_dir and any("trajectory=kitti" in str(o) for o in self.cfg.data):
            # refused here, not before: a study whose stages are cached rewrites its report
            # without the poses
            raise ValueError("poses_dir: set it to KITTI's poses/ directory (00.txt ... 10.txt)")
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
        self,
        name: str,
        extra: list[str],
        steps: int | None = None,
        max_time: str | None = None,
        settings: dict[str, Any] | None = None,
    ) -> DictConfig:
        """The ``train`` config of model ``name``, composed once per model: the study's data,
        the convergence rule with its caps (``steps``; ``max_time``, Lightning's
        "DD:HH:MM:SS"), then ``extra`` (config choices and study blocks), then ``settings``
        (dotted key → number, set as numbers: ``{"model.loss.w_s": 100.0}``). ``steps`` None:
        the config the model was (or will be) trained from, for its data; composed with one
        step when the model has not been composed yet (its data are the same)."""
        key = (name, tuple(str(e) for e in extra), tuple(sorted((settings or {}).items())))
        if steps is None:
            if key not in self._configs:
                self._configs[key] = self._compose(name, extra, 1, None, settings)
            return self._configs[key]
        cfg = self._compose(name, extra, steps, max_time, settings)
        self._configs[key] = cfg
        return cfg

    def _compose(
        self,
        name: str,
        extra: list[str],
        steps: int,
        max_time: str | None,
        settings: dict[str, Any] | None,
    ) -> DictConfig:
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
        cfg = compose("train", ov)
        for key, value in (settings or {}).items():
            OmegaConf.update(cfg, key, value, merge=False)
        return cfg

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
        cfg = self.train_config("main", [*extra, CENTRAL_OFFSETS])
        return self.datamodule(cfg, splits=("test",))

    def train(
        self,
        name: str,
        extra: list[str],
        steps: int,
        max_time: str | None = None,
        settings: dict[str, Any] | None = None,
    ) -> Result:
        """Train (or resume) model ``name`` under the convergence rule, capped at ``steps`` and
        ``max_time``; its best checkpoint by ``val/ate`` (the last under an equal budget or a
        rule on another metric), the steps it ran, whether it converged and why, its curve,
        and the resolved config it trained from (paths as a reader finds them)."""
        from mfg_lightning.run.training import train

        cfg = self.train_config(name, extra, steps, max_time, settings)
        digest = training_digest(cfg)
        if (twin := self._trained_as(digest, name)) is not None:
            # another stage trained this very model: one training serves both
            print(f"{name}: the same training config as {twin['name']}: not trained again",
                  flush=True)  # fmt: skip
            return {**twin, "same_as": twin["name"], "name": name}
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
        resolved = OmegaConf.load(out / "config.yaml")
        precision = str(resolved.trainer.get("precision", "32-true"))
        result = {
            "name": name,
            "overrides": list(extra),
            "settings": dict(settings or {}),
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
            # the run's own config.yaml (resolved, ``auto`` made concrete)
            "config": portable_config(OmegaConf.to_container(resolved, resolve=True)),
        }
        atomic_write_text(out / TRAINED, json.dumps({"digest": digest, **result}) + "\n")
        return result

    def _trained_as(self, digest: str, name: str) -> Result | None:
        """The result of a model of this work_dir trained from an equal training config
        (:func:`training_digest`) under another name, or None."""
        for path in sorted((self.work / "models").glob(f"*/{TRAINED}")):
            if path.parent.name == name:
                continue
            try:
                done = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError):
                continue
            if done.pop("digest", None) == digest and done.get("name") != name:
                return done
        return None

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
                trained.get("time_cap"), trained.get("settings"),
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


#: The file beside a trained model that records its result and its training config's digest.
TRAINED = "study_trained.json"


def training_digest(cfg: DictConfig) -> str:
    """A digest of a composed ``train`` config as written, without where its run goes
    (``paths.output_dir``): two models of equal digests are one model (same data, model,
    seed, rule, caps and trainer)."""
    import hashlib

    tree = OmegaConf.to_container(cfg, resolve=False)
    tree.get("paths", {}).pop("output_dir", None)
    return hashlib.sha256(json.dumps(tree, sort_keys=True, default=str).encode()).hexdigest()


def portable_config(tree: Any) -> Any:
    """A resolved config with every absolute path as a reader finds it (relative to the working
    directory, ``../…`` beside it, ``<cache>/…``; :func:`mfg_lightning.core.paths.portable_path`):
    committed results name no path of this machine."""
    from mfg_lightning.flow.cache import default_cache_dir

    if isinstance(tree, dict):
        return {k: portable_config(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [portable_config(v) for v in tree]
    if isinstance(tree, str) and tree.startswith(("/", "~")):
        return portable_path(str(Path(tree).expanduser()), Path.cwd(), default_cache_dir())
    return tree


def to_container(x: Any) -> Any:
    return OmegaConf.to_container(x, resolve=True) if OmegaConf.is_config(x) else x
