"""How the learned flow trained: the validation curve of a ``python -m mfg_lightning.train_flow``
run, where it stands and what it cost.

Reads a run directory (``--run``: its TensorBoard events, ``metrics.json``, ``config.yaml`` and
the exported ``flow_net.pt``'s provenance) into ``--work/curve.json`` (committed: a fresh clone
rebuilds the section without the run), then writes one section of ``<out>/flow_quality.md``
between ``<!-- flow-training:start -->`` and ``<!-- flow-training:end -->``: the run's settings
and cost, its validation end-point error at every validation (all pixels, per offset, per
region) and a figure of the curve beside DIS medium's validation EPE (the same worlds' tails).

``python bench/flow_training.py --run outputs/train_flow/<run>`` (seconds); without ``--run``
the committed ``curve.json`` is read.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import RESULTS_DIR, Report, add_common_arguments, fmt, markdown_table

MARKER = "flow-training"
HEADING = "How the learned flow trained"
#: The validation scalars of FlowLitModule, in the table's order.
CURVE_KEYS = (
    "val/epe", "val/epe_+1", "val/epe_-1", "val/epe_+2", "val/epe_-2",
    "val/epe/road", "val/epe/structure", "val/epe/moving", "val/epe/far", "val/fl",
)  # fmt: skip
#: ... and on the non-occluded pixels alone (logged by runs whose pairs carry the renderer's
#: visibility marks; the table shows them where a run has them).
NOC_KEYS = ("val/epe_noc", "val/fl_noc")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", type=Path, default=None, help="a train_flow run directory")
    p.add_argument("--work", type=Path, default=RESULTS_DIR / "flow_training",
                   help="where curve.json is kept")  # fmt: skip
    p.add_argument("--dis-val-epe", type=float, default=None,
                   help="DIS medium's validation EPE for the figure (default: "
                   "flow_quality.md's)")  # fmt: skip
    add_common_arguments(p)
    return p.parse_args(argv)


def read_run(run: Path) -> dict[str, Any]:
    """A run's validation curve, training EPE, settings and cost."""
    from omegaconf import OmegaConf
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mfg_lightning.flow.learned import load_weights

    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    tags = set(events.Tags()["scalars"])
    curve: dict[int, dict[str, float]] = {}
    for key in (*CURVE_KEYS, *NOC_KEYS):
        for e in events.Scalars(key) if key in tags else []:
            if e.step > 0:  # (step 0: the final metrics logged again with the hyperparameters)
                curve.setdefault(int(e.step), {})[key] = float(e.value)
    train = [(int(e.step), float(e.value)) for e in events.Scalars("train/epe")] if (
        "train/epe" in tags) else []  # fmt: skip
    done = run / "metrics.json"  # (absent while the run is still training)
    metrics = json.loads(done.read_text()) if done.is_file() else {}
    cfg = OmegaConf.load(run / "config.yaml")
    provenance: dict[str, Any] = {}
    if (run / "flow_net.pt").is_file():
        provenance = load_weights(run / "flow_net.pt")[1]
    ds = cfg.dataset
    return {
        "curve": [{"step": s, **v} for s, v in sorted(curve.items())],
        "train_epe": train,
        "train_seconds": metrics.get("train_seconds"),
        "checkpoint": metrics.get("checkpoint"),
        "cpu_kind": metrics.get("cpu_kind"),
        "commit": provenance.get("commit") or metrics.get("git_commit"),
        "command": provenance.get("command"),
        "steps": int(cfg.trainer.max_steps),
        "batch_size": int(ds.batch_size),
        "crop": list(cfg.model.get("crop") or []),
        "lr": float(cfg.model.optimizer.lr),
        "sequences": [f"{int(s):02d}" for s in ds.train_sequences] if ds.trajectory == "kitti" else
        int(ds.train_sequences),
        "frame_stride": int(ds.frame_stride),
        "val_every": int(ds.val_every),
        "offsets": list(ds.offsets),
    }  # fmt: skip


def dis_val_epe(out: Path) -> float | None:
    """DIS medium's validation EPE at +1 (all pixels, every frame of the tails) from
    flow_quality.md's first table (its ``val`` row, or ``val``'s ``all`` row where the table
    gives the ``noc`` and ``all`` pixels a row each)."""
    path = out / "flow_quality.md"
    if not path.is_file():
        return None
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) > 13 and cells[0] == "val" and "medium" in cells[1:3]:
            if cells[1] == "noc":
                continue
            # EPE all: the 13th cell, one later with the column naming the pixels
            return float(cells[11 + cells.index("medium")])
    return None


def figure(data: dict, dis: float | None, path: Path) -> Path:
    """The validation curve: EPE (all, +1, +2) against steps; DIS medium's +1 EPE on the
    validation tails (flow_quality.md's first table) as a line."""
    from matplotlib.figure import Figure

    from mfg_lightning.pictures.grids import save_png
    from mfg_lightning.pictures.plots import figure_rgb

    fig = Figure(figsize=(7.5, 4.2), dpi=110, layout="constrained")
    ax = fig.add_subplot()
    steps = [p["step"] for p in data["curve"]]
    for key, label in (("val/epe", "all offsets"), ("val/epe_+1", "+1"), ("val/epe_+2", "+2")):
        ax.plot(steps, [p.get(key) for p in data["curve"]], marker="o", label=f"learned, {label}")
    if data["train_epe"]:
        s, v = zip(*data["train_epe"], strict=True)
        ax.plot(s, v, color="0.75", lw=0.8, label="learned, training crops (finest level)",
                zorder=0)  # fmt: skip
    if dis is not None:
        ax.axhline(
            dis,
            color="k",
            ls="--",
            lw=1,
            label=f"DIS medium, +1 ({dis:.2f} px, every validation frame)",
        )
    ax.set_xlabel("training step")
    ax.set_ylabel("validation end-point error (px, 192 × 512)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("The learned flow on the validation tails of the training worlds")
    return save_png(figure_rgb(fig), path)


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    report = Report("flow_quality", "Flow of rendered worlds", args.out)
    args.work.mkdir(parents=True, exist_ok=True)
    cached = args.work / "curve.json"
    if args.run is not None:
        data = read_run(args.run)
        cached.write_text(json.dumps(data, indent=1) + "\n")
    elif cached.is_file():
        data = json.loads(cached.read_text())
    else:
        raise SystemExit(f"error: no --run given and no {cached}")
    out = report.out_dir
    dis = args.dis_val_epe if args.dis_val_epe is not None else dis_val_epe(out)
    png = figure(data, dis, out / "flow_quality" / "learned_training.png")
    noc = any(k in p for p in data["curve"] for k in NOC_KEYS)
    keys = (*CURVE_KEYS, *NOC_KEYS) if noc else CURVE_KEYS
    rows = []
    for p in data["curve"]:
        rows.append([str(p["step"]), *(fmt(p.get(k), 1 if "/fl" in k else 2)
                                       for k in keys)])  # fmt: skip
    heads = ["step", "EPE all", "+1", "-1", "+2", "-2", "road", "structure", "moving", "far",
             "Fl all (%)", *(("EPE noc", "Fl noc (%)") if noc else ())]  # fmt: skip
    seqs = data["sequences"]
    where = (f"the rendered worlds of KITTI's {', '.join(seqs)}" if isinstance(seqs, list)
             else f"{seqs} procedural worlds")  # fmt: skip
    minutes = (data.get("train_seconds") or 0) / 60
    report.add(
        f"`{data.get('command') or 'python -m mfg_lightning.train_flow'}` (commit "
        f"`{(data.get('commit') or '?')[:7]}`): {data['steps']} steps of batch "
        f"{data['batch_size']}, "
        + (f"random {' × '.join(map(str, data['crop']))} crops" if data["crop"] else "whole frames")
        + f", Adam at {data['lr']:g} decayed to 0, on {where} (training pairs from every "
        f"{data['frame_stride']}th frame without the validation tails, offsets "
        f"{', '.join(f'{o:+d}' for o in data['offsets'])}); validated on every "
        f"{data['val_every']}th frame of the tails, whole frames at 192 × 512. {minutes:.0f} min "
        f"on 2 {data.get('cpu_kind') or '?'} cores, rendering excluded. The shipped weights "
        f"are its {data.get('checkpoint') or 'best'} checkpoint (the lowest validation EPE). "
        f"![validation curve]({png.relative_to(out).as_posix()})\n\n"
        "Validation end-point error (px) at every validation, by offset and region, on all "
        "pixels whose exact flow is known"
        + (
            " and on the non-occluded ones (noc)"
            if noc
            else " (the run predates the visibility marks: no noc scores)"
        )
        + ":\n\n"
        + markdown_table(heads, rows)
    )
    return report.write_section(MARKER, HEADING)


if __name__ == "__main__":
    main()
