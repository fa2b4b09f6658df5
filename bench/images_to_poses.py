"""Images to poses: how fast does ``python -m mfg_lightning.predict`` turn a folder of frames
into a trajectory, against DIS + the best classical method on the same frames, and where does
the time go?

Frames: a procedural drive of the synthetic worlds (``dataset=synthetic flow=dis``'s persistent
world and renderer, :mod:`mfg_lightning.data.rendered`) rendered at each ``--sizes`` and written
as PNG files into a temporary folder with the camera's intrinsics, the input of
``dataset=image_folder``. Model: the default config's MFG (48 × 128, M = 1000), trained for
``--train-steps`` on the synthetic exact flow and saved as a checkpoint: its accuracy is
irrelevant here, its cost is the trained model's.

Measured per image size, interleaved, the median of ``--repeats`` after one warm-up round:

1. end to end: :func:`mfg_lightning.run.prediction.predict` (what ``python -m
   mfg_lightning.predict dataset=image_folder`` runs, in this process: the checkpoint, the
   DataModule, Lightning's predict loop, the DIS and RGB caches, the output files) on the whole
   folder, each run with an empty cache (a first run on a folder); and on its first two frames,
   the call's start-up.
2. the stages, on the same frames with the same functions the predict path calls: read (the
   dataset's frame decoding, as its loader does it: PNG, resize to the input, grey), flow (DIS
   and the resize to the input), network (the module's forward at the predict batch size),
   recovery (:func:`~mfg_lightning.core.geometry.recover_motion`), composition
   (:meth:`mfg_lightning.run.prediction.PredictedSequence.trajectory`); and the classical method
   frame by frame on the same flows (:func:`mfg_lightning.motion.baselines.
   essential_matrix_motion` with MAGSAC++, as ``mfg_lightning.analysis.scoring`` scores it),
   composed the same way.

The classical method is MAGSAC++ (OpenCV's essential matrix), the classical row with the lowest
ATE on both test sequences in ``accuracy.md``'s DIS-flow table and ``reproduction.md``.

Written as the section between ``<!-- images-to-poses:start/end -->`` of ``<out>/throughput.md``
(which ``bench/throughput.py`` keeps), and by a full run into ``bench/results`` as one line of
docs/evaluation.md between the same markers.

``python bench/images_to_poses.py`` (about 4 minutes on 2 quiet CPU cores); ``--tiny`` for a
smoke run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (
    REPO,
    TINY_OVERRIDES,
    Report,
    add_common_arguments,
    fmt,
    markdown_table,
    write_marked,
)
from images_to_poses_parts.timing import (
    CLASSICAL,
    CLASSICAL_STAGES,
    MFG_STAGES,
    STAGE_NOTES,
    time_predict,
    time_stages,
)

#: The marker of this script's section in throughput.md and of its line in docs/evaluation.md.
MARKER = "images-to-poses"
#: The page whose line a full run rewrites.
DOCS_PAGE = REPO / "docs" / "evaluation.md"
HEADING = "Images to poses: `predict` on a folder of PNG frames, against DIS + MAGSAC++"
E2E_STEPS = 2  # training steps of the end-to-end checkpoint (its cost is measured, not accuracy)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=101, help="frames per folder (pairs + 1)")
    p.add_argument("--sizes", nargs="+", default=["192x512", "376x1241"], help="image sizes, HxW")
    p.add_argument("--repeats", type=int, default=5, help="timed rounds (after one warm-up)")
    p.add_argument("--train-steps", type=int, default=20, help="the checkpoint's training")
    p.add_argument("--preset", default="medium", help="DIS preset (the image folder's default)")
    p.add_argument("--learned-sizes", nargs="*", default=["192x512"],
                   help="image sizes at which flow=learned (the shipped weights) and an "
                   "end-to-end checkpoint's network run, HxW (none: DIS only)")  # fmt: skip
    p.add_argument("--readme", type=Path, default=None, help="page to update (default: "
                   "docs/evaluation.md when writing into bench/results, else none)")  # fmt: skip
    add_common_arguments(p, "torch and OpenCV threads (default: all)")
    args = p.parse_args(argv)
    args.sizes = [parse_size(s) for s in args.sizes]
    args.learned_sizes = [parse_size(s) for s in args.learned_sizes]
    if args.tiny:
        args.frames, args.sizes, args.repeats, args.train_steps = 6, [(48, 128)], 1, 2
        args.learned_sizes = [(48, 128)] if args.learned_sizes else []
    if args.frames < 4:
        p.error("--frames: at least 4")
    return args


def parse_size(text: str) -> tuple[int, int]:
    """``"192x512"`` → ``(192, 512)``."""
    try:
        h, w = (int(v) for v in text.lower().replace("×", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"an image size is HxW, e.g. 192x512: {text!r}") from None
    return h, w


def make_checkpoint(path: Path, tiny: bool, steps: int, end_to_end: bool = False) -> Path:
    """The default config's MFG (the tiny one with ``tiny``) trained ``steps`` steps on the
    synthetic exact flow, in 32-bit, saved as a checkpoint ``predict`` reads; ``end_to_end``:
    ``experiment=end_to_end`` (the flow network from its shipped weights and MFG together, no
    frozen warm-up) on rendered frame pairs."""
    import lightning as L
    import torch
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose
    from mfg_lightning.run.runs import build_model

    e2e = ["experiment=end_to_end", "model.freeze_flow_steps=0",
           f"paths.cache_dir={path.parent / 'e2e-cache'}"] if end_to_end else []  # fmt: skip
    overrides = [*e2e, f"paths.output_dir={path.parent}", "dataset.train_sequences=1",
                 "dataset.test_sequences=1", f"dataset.sequence_length={16 if e2e else 64}",
                 *(TINY_OVERRIDES if tiny else ())]  # fmt: skip
    cfg = compose("train", overrides)
    torch.manual_seed(0)
    model = build_model(cfg)
    trainer = L.Trainer(
        accelerator="cpu", devices=1, max_steps=steps, precision="32-true", logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        limit_val_batches=0, num_sanity_val_steps=0, default_root_dir=path.parent,
    )  # fmt: skip
    trainer.fit(model, datamodule=instantiate(cfg.dataset))
    trainer.save_checkpoint(path)
    return path


def render_folder(folder: Path, height: int, width: int, frames: int, tiny: bool) -> list[float]:
    """Render ``frames`` consecutive frames of a procedural drive at ``height × width`` into
    ``folder/000000.png`` …; the camera's ``(fx, fy, cx, cy)`` in pixels."""
    import cv2
    from hydra.utils import instantiate

    from mfg_lightning.core.config import compose

    cfg = compose("train", [
        "flow=dis", f"flow.height={height}", f"flow.width={width}", "dataset.train_sequences=1",
        "dataset.test_sequences=1", f"dataset.sequence_length={frames}",
        f"paths.output_dir={folder.parent}", f"paths.cache_dir={folder.parent / 'render-cache'}",
        *(TINY_OVERRIDES if tiny else ()),
    ])  # fmt: skip
    dataset = instantiate(cfg.dataset).dataset("test")
    seq = next(iter(dataset.trajectories))
    folder.mkdir(parents=True)
    for k in range(frames):
        rgb = dataset.render(seq, k).rendered.rgb.permute(1, 2, 0).numpy()
        if not cv2.imwrite(str(folder / f"{k:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {folder / f'{k:06d}.png'}")
    return [float(v) for v in dataset.image_intrinsics]


def predict_config(
    ckpt: Path, folder: Path, camera: list[float], work: Path, args, flow: str = "dis"
) -> Any:
    """The config of ``python -m mfg_lightning.predict`` on ``folder`` (``dataset=image_folder``),
    its outputs and an empty flow cache under ``work``; ``flow``: ``dis`` (at ``args.preset``),
    ``learned`` (the shipped weights) or ``end_to_end`` (``ckpt``'s own network, as ``predict``
    reads an end-to-end checkpoint under ``flow=learned``)."""
    from mfg_lightning.core.config import compose

    fx, fy, cx, cy = camera
    input_hw = ["dataset.height=32", "dataset.width=64"] if args.tiny else []
    return compose("predict", [
        f"ckpt_path={ckpt}", "dataset=image_folder", f"dataset.data_root={folder}",
        f"dataset.fx={fx}", f"dataset.fy={fy}", f"dataset.cx={cx}", f"dataset.cy={cy}",
        *input_hw, *{"dis": [f"flow.preset={args.preset}"], "learned": ["flow=learned"],
                     "end_to_end": ["flow=learned", f"flow.weights={ckpt}"]}[flow],
        f"paths.output_dir={work / 'run'}",
        f"paths.cache_dir={work / 'cache'}", "trainer.accelerator=cpu",
        "++trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
    ])  # fmt: skip


@dataclass
class SizeResult:
    """The medians of one image size."""

    height: int
    width: int
    pairs: int
    flow: str  # dis, learned or end_to_end
    predict_s: float  # the whole folder
    startup_s: float  # the first two frames (start-up and one pair)
    mfg: dict[str, float]  # seconds per pass, per stage
    classical: dict[str, float]

    def marginal_ms(self) -> float:
        """``predict``'s milliseconds per frame after its start-up."""
        return 1000 * (self.predict_s - self.startup_s) / (self.pairs - 1)

    def ms(self, stages: dict[str, float]) -> dict[str, float]:
        return {k: 1000 * v / self.pairs for k, v in stages.items()}


def measure_size(
    ckpt: Path, folder: Path, camera: list[float], work: Path, args, flow: str = "dis"
) -> SizeResult:
    """The medians of one image size and flow: one warm-up round, then ``args.repeats`` rounds
    of predict on the folder, predict on its first two frames and the staged pass, interleaved,
    each with empty caches."""
    import shutil

    two = folder.parent / f"{folder.name}-2"
    if not two.exists():
        two.mkdir()
        for path in sorted(folder.glob("*.png"))[:2]:
            shutil.copy(path, two / path.name)
    whole, start, passes = [], [], []
    for r in range(args.repeats + 1):
        round_dir = work / f"round{r}"
        cfgs = [predict_config(ckpt, f, camera, round_dir / n, args, flow)
                for f, n in ((folder, "whole"), (two, "two"), (folder, "stages"))]  # fmt: skip
        times = (time_predict(cfgs[0]), time_predict(cfgs[1]), time_stages(cfgs[2]))
        shutil.rmtree(round_dir)
        if r == 0:
            continue  # the warm-up
        whole.append(times[0])
        start.append(times[1])
        passes.append(times[2])
        mfg_s = sum(times[2].mfg.values())
        print(f"{folder.name} {flow} round {r}: predict {times[0]:.2f} s, its start-up "
              f"{times[1]:.2f} s, stages {mfg_s:.2f} s", flush=True)  # fmt: skip

    def median_stages(which: str) -> dict[str, float]:
        keys = getattr(passes[0], which)
        return {k: statistics.median(getattr(p, which)[k] for p in passes) for k in keys}

    return SizeResult(
        *parse_size(folder.name), passes[0].pairs, flow, statistics.median(whole),
        statistics.median(start), median_stages("mfg"), median_stages("classical"),
    )  # fmt: skip


def rate(ms: float) -> str:
    """Frames per second of ``ms`` milliseconds per frame (– when not positive: a difference of
    two timings on a loaded machine)."""
    return fmt(1000 / ms, 1) if ms > 0 else "–"


def share(part: float, whole: float) -> str:
    return f"{100 * part / whole:.0f} %" if whole > 0 else "–"


#: How the tables name each flow.
FLOW_NAMES = {"dis": "DIS", "learned": "learned (`flow=learned`)",
              "end_to_end": "end-to-end (`experiment=end_to_end`'s network)"}  # fmt: skip


def rates_table(results: list[SizeResult], kind: str) -> str:
    rows = []
    for r in results:
        whole_ms = 1000 * r.predict_s / r.pairs
        mfg_ms, classical_ms = (sum(r.ms(s).values()) for s in (r.mfg, r.classical))
        flow = FLOW_NAMES[r.flow]
        for name, ms in (
            ("MFG: `predict`, end to end (the whole call)", whole_ms),
            ("MFG: `predict` after its start-up", r.marginal_ms()),
            ("MFG: its stages alone", mfg_ms),
            (f"{flow.split()[0]} flow + {CLASSICAL[0]}: its stages", classical_ms),
        ):
            rows.append([f"{r.height} × {r.width}", flow, kind, name, rate(ms), fmt(ms, 2)])
    heads = ["image size", "flow", "CPU", "pipeline", "frames/s", "ms / frame"]
    return markdown_table(heads, rows)


def stages_table(r: SizeResult) -> str:
    mfg, classical = r.ms(r.mfg), r.ms(r.classical)
    marginal, classical_total = r.marginal_ms(), sum(classical.values())

    def cells(ms: float | None, whole: float) -> list[str]:
        return ["–", "–"] if ms is None else [fmt(ms, 2), share(ms, whole)]

    rows = [
        [stage, STAGE_NOTES[stage], *cells(mfg.get(stage), marginal),
         *cells(classical.get(stage), classical_total)]
        for stage in dict.fromkeys(MFG_STAGES + CLASSICAL_STAGES)
    ]  # fmt: skip
    rest = "Lightning's loop, collation, the flow and RGB caches, the output files"
    rows.append(["the rest of `predict`", rest, *cells(marginal - sum(mfg.values()), marginal),
                 *cells(None, 0)])  # fmt: skip
    total = "MFG: `predict` after its start-up; classical: the sum"
    rows.append(["total", total, *cells(marginal, marginal), *cells(classical_total,
                 classical_total)])  # fmt: skip
    header = ["stage", "what", "MFG (ms / frame)", "MFG share", "classical (ms / frame)",
              "classical share"]  # fmt: skip
    return markdown_table(header, rows)


def readme_line(results: list[SizeResult], kind: str, cores: int, date: str, link: str) -> str:
    """The docs' one line: the first size's end-to-end rate beside the classical one (and the
    learned flow's and the end-to-end network's at that size, when measured), with the machine
    and ``date`` (YYYY-MM-DD) beside every rate; ``link``: throughput.md, relative to the page."""
    r = results[0]
    classical_ms = sum(r.ms(r.classical).values())
    words = {"learned": "with `flow=learned`", "end_to_end": "end to end"}
    also = "".join(
        f"; {words[x.flow]} {rate(x.marginal_ms())} frames/s"
        for x in results if x.flow in words and (x.height, x.width) == (r.height, r.width)
    )  # fmt: skip
    return (
        f"Images to poses: `predict` on a folder of {r.height} × {r.width} PNG frames runs at "
        f"{rate(r.marginal_ms())} frames/s after a {r.startup_s:.1f} s start-up, on {cores} "
        f"{kind} CPU cores ({date}). DIS + MAGSAC++ runs at {rate(classical_ms)} frames/s{also} "
        f"there ([throughput]({link})).\n"
    )


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    import os

    import cv2
    import torch

    from mfg_lightning.core.machine import cpu_kind

    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    if args.threads:
        torch.set_num_threads(args.threads)
        cv2.setNumThreads(args.threads)
    kind = cpu_kind()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    report = Report("throughput", "Throughput: training, inference, data, memory", args.out)
    results = []
    with tempfile.TemporaryDirectory(prefix="mfg-bench-images-") as tmp_name:
        tmp = Path(tmp_name)
        start = time.perf_counter()
        ckpt = make_checkpoint(tmp / "mfg.ckpt", args.tiny, args.train_steps)
        e2e = args.learned_sizes and make_checkpoint(tmp / "e2e" / "e.ckpt", args.tiny, E2E_STEPS,
                                                     end_to_end=True)  # fmt: skip
        print(f"checkpoints: {time.perf_counter() - start:.1f} s", flush=True)
        for h, w in args.sizes:
            start = time.perf_counter()
            folder = tmp / f"{h}x{w}"
            camera = render_folder(folder, h, w, args.frames, args.tiny)
            print(f"{args.frames} frames rendered at {h} × {w}: "
                  f"{time.perf_counter() - start:.1f} s", flush=True)  # fmt: skip
            results.append(measure_size(ckpt, folder, camera, tmp / f"work-{h}x{w}", args))
            if (h, w) in args.learned_sizes:
                results += [measure_size(c, folder, camera, tmp / f"work-{h}x{w}-{f}", args, f)
                            for c, f in ((ckpt, "learned"), (e2e, "end_to_end"))]  # fmt: skip
    model = "the tiny test model (32 × 64 input)" if args.tiny else "the default MFG (48 × 128"
    model += "" if args.tiny else " input, M = 1000)"
    report.add(
        f"{args.frames} consecutive frames of a procedural drive through the synthetic worlds "
        f"(the renderer of `flow=dis`), written as PNG files at each image size; {model} from "
        f"a checkpoint trained {args.train_steps} steps (its accuracy is not what is measured "
        f"here); DIS `{args.preset}` at the image size, and `flow=learned` (the shipped "
        "weights of the framework's PWC-Net-design network, `docs/flow.md`) and an end-to-end "
        f"checkpoint's network (`experiment=end_to_end`, {E2E_STEPS} steps from those weights) at "
        + (", ".join(f"{h} × {w}" for h, w in args.learned_sizes) or "no size")
        + f"; CPU **{kind}** ({cores} cores, "
        f"{torch.get_num_threads()} torch threads). Medians of {args.repeats} interleaved rounds "
        "after one warm-up round, each run with an empty flow cache (a first run on a folder). "
        "A frame is one pose: the pairs k → k + 1 of the folder."
    )
    report.add(rates_table(results, kind))
    report.add(
        "*End to end*: `mfg_lightning.run.prediction.predict` in this process, what `python -m "
        "mfg_lightning.predict dataset=image_folder` runs after its imports (checkpoint, "
        "DataModule, Lightning's predict loop, the flow and its cache, network, recovery, "
        "composition, the KITTI/TUM/CSV files). *After its start-up*: (the folder's time − the "
        "time on its first two frames) / (pairs − 1), the rate a long sequence approaches; "
        "start-up "
        + ", ".join(f"{r.startup_s:.2f} s at {r.height} × {r.width} ({r.flow})" for r in results)
        + ". *Stages*: each timed alone on the same frames with the functions the predict path "
        "calls (below); the classical pipeline has no entry point: its rate is its stages' sum, "
        f"without loader, caches or files. {CLASSICAL[0]} reads the same flows at the model "
        "input (every 2nd pixel, as `bench/accuracy.py` scores it), the lowest ATE of the "
        "classical methods on DIS flow (`accuracy.md`, `reproduction.md`); without ground "
        "truth its translation keeps unit length."
    )
    for r in results:
        report.add(f"### Where the time goes, {r.height} × {r.width}, {FLOW_NAMES[r.flow]} flow"
                   f"\n\n{stages_table(r)}")  # fmt: skip
    report.add("Shares: of `predict` after its start-up (MFG) and of the stages' sum "
               "(classical). *The rest of `predict`*: its time after start-up less its stages. "
               "Read and flow are one measurement shared by both pipelines.")  # fmt: skip
    path = report.write_section(MARKER, HEADING)
    # The docs' line only from a real run into bench/results (or a page named).
    readme = args.readme or (DOCS_PAGE if args.out is None and not args.tiny else None)
    if readme is not None:
        link = os.path.relpath(REPO / "bench" / "results" / "throughput.md", readme.parent)
        date = time.strftime("%Y-%m-%d", time.gmtime())
        write_marked(readme, MARKER, readme_line(results, kind, cores, date, link))
    return path


if __name__ == "__main__":
    main()
