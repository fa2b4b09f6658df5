"""Export the synthetic worlds as dataset trees in the published layouts (KITTI odometry,
Virtual KITTI 1.3.1 and 2.0.3), readable by ``dataset=kitti|vkitti`` and by other people's tools.

``python -m mfg_lightning.data.export layout=kitti|vkitti out=<dir> [overwrite=true]
[version=1|2] [height=H width=W] [dataset.…]``

The trajectories, seeds and world settings are those of ``dataset=synthetic`` (its config is
composed, so ``dataset.trajectory=kitti dataset.poses_dir=…``, ``dataset.train_sequences``,
``dataset.sequence_length``, ``dataset.max_frames`` … apply): each trajectory's persistent
:class:`~mfg_lightning.scene.worlds.World` is the one ``dataset=synthetic flow=dis`` renders
(same name and seed), every frame is rendered once
(:func:`~mfg_lightning.scene.render.render_frame`) and, for Virtual KITTI, the forward flow of
frame ``t → t + 1`` is the exact flow from that rendering
(:func:`~mfg_lightning.scene.render.exact_flow`). Layouts (``docs/formats.md``)::

    layout=kitti (any size; default KITTI 00's 1241 × 376 and its P2)
    sequences/XX/image_2/000000.png …   8-bit RGB
    sequences/XX/calib.txt               P0–P3, Tr (write_kitti_calib)
    sequences/XX/times.txt               10 Hz
    poses/XX.txt                         T_world_cam, the first pose the identity

    layout=vkitti version=1 (1242 × 375, fx = fy = 725, cx = 620.5, cy = 187)
    vkitti_1.3.1_rgb/<world>/clone/%05d.png
    vkitti_1.3.1_depthgt/<world>/clone/%05d.png        16-bit cm, 65535 = sky
    vkitti_1.3.1_flowgt/<world>/clone/%05d.png         frames 0 … N−2, B = 0 invalid
    vkitti_1.3.1_extrinsicsgt/<world>_clone.txt        world-to-camera

    layout=vkitti version=2 (any size; the same camera scaled)
    vkitti_2.0.3_rgb/SceneXX/clone/frames/rgb/Camera_0/rgb_%05d.jpg
    vkitti_2.0.3_depth/…/depth_%05d.png, vkitti_2.0.3_forwardFlow/…/flow_%05d.png
    vkitti_2.0.3_textgt/SceneXX/clone/extrinsic.txt, intrinsic.txt

Names: KITTI sequences are the training trajectories then the test ones, ``00``, ``01``, …
(the default 9 + 2 give the paper's split, train 00–08, test 09 and 10), or the KITTI names when
``dataset.trajectory=kitti``. Virtual KITTI worlds are the test trajectories then the training
ones, ``0001 0002 0006 0018 0020`` (the default 1 + 4 give the paper's egomotion split, test
0001); at most five. Sky is the far plane (655.35 m) in depth and invalid in the flow, as in
Virtual KITTI; flow that leaves the encoding's range (``±(W − 1)``, ``±(H − 1)``) or points behind
the next camera is invalid too. Not written: image_0/1/3 (only ``image_2`` is rendered),
Virtual KITTI's scene and tracking ground truth, other variations than ``clone``.

Writing: every file atomically (temporary file, then rename: an interrupted export leaves no
half-written file), nothing outside ``out``. ``out`` must be empty or new; ``overwrite=true``
replaces a previous export there (recognised by its manifest, ``mfg_export.json``, which lists
what it wrote and says whether it finished), never other files.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from mfg_lightning.core import geometry
from mfg_lightning.core.config import CONFIG_DIR
from mfg_lightning.core.errors import exit_on_unknown_choice, exit_on_user_error

log = logging.getLogger(__name__)

__all__ = [
    "MANIFEST",
    "KittiTree",
    "Sequence",
    "VkittiTree",
    "export",
    "synthetic_sequences",
]

LAYOUTS = ("kitti", "vkitti")
#: The manifest a tree's root gets: what was written, from which config, and whether it finished.
MANIFEST = "mfg_export.json"
_MANIFEST_FORMAT = 1
#: KITTI odometry's frame rate (times.txt).
FRAME_RATE_HZ = 10.0
#: Virtual KITTI's native image size (height, width).
VKITTI_SIZE = (375, 1242)
VARIATION = "clone"


@dataclass(frozen=True)
class Sequence:
    """One trajectory to export.

    Attributes:
        name: its name in the tree (``"00"`` or ``"0001"``).
        world: the synthetic trajectory's name (``"train03"``, KITTI ``"07"``): the world's.
        seed: the world's seed (as ``dataset=synthetic``: test trajectories get another one).
        poses: ``(N, 4, 4)`` float64 ``T_world_cam`` the frames are rendered at.
    """

    name: str
    world: str
    seed: int
    poses: torch.Tensor

    @property
    def relative_to_first(self) -> np.ndarray:
        """``(N, 4, 4)`` float64 poses in the first camera's coordinates (the first the
        identity), projected onto SE(3): what the pose files hold. KITTI's own pose files carry
        rotations to ~7 digits; exact rotations make world-to-camera and back exact too."""
        first = geometry.invert_pose(self.poses[0])
        return geometry.project_to_se3(first[None] @ self.poses).numpy()


def synthetic_sequences(datamodule: Any, layout: str) -> list[Sequence]:
    """The trajectories of a :class:`~mfg_lightning.data.synthetic.SyntheticDataModule`, named
    for ``layout`` (see the module docstring).

    Raises:
        ValueError: Virtual KITTI with more than five trajectories, a KITTI name in both splits,
            or no trajectory at all.
    """
    from mfg_lightning.data.vkitti import WORLDS

    order = ("train+val", "test") if layout == "kitti" else ("test", "train+val")
    found = []
    for split in order:
        ds = datamodule.build_dataset(split)  # flow=exact: only the index is built
        found += [(seq, ds.seed, poses) for seq, poses in ds.trajectories.items()]
    if not found:
        raise ValueError("dataset.train_sequences / dataset.test_sequences: nothing to export")
    if layout == "vkitti":
        if len(found) > len(WORLDS):
            raise ValueError(
                f"layout=vkitti: {len(found)} trajectories (dataset.train_sequences + "
                f"dataset.test_sequences) but Virtual KITTI has {len(WORLDS)} worlds "
                f"({' '.join(WORLDS)}); export at most {len(WORLDS)}"
            )
        names = list(WORLDS[: len(found)])
    elif datamodule.trajectory == "kitti":
        names = [seq for seq, _, _ in found]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(
                f"KITTI sequence(s) {twice} are in both dataset.train_sequences and "
                "dataset.test_sequences: one tree holds each sequence once"
            )
    else:
        digits = max(2, len(str(len(found) - 1)))
        names = [f"{i:0{digits}d}" for i in range(len(found))]
    return [
        Sequence(name, seq, int(seed), poses.to(torch.float64))
        for name, (seq, seed, poses) in zip(names, found, strict=True)
    ]


# --------------------------------------------------------------------------------------------
# Trees
# --------------------------------------------------------------------------------------------


class KittiTree:
    """Writes KITTI odometry: ``sequences/XX/{image_2/*.png, calib.txt, times.txt}``,
    ``poses/XX.txt``, at ``height × width`` with KITTI's camera scaled to it."""

    layout = "kitti"
    version = None

    def __init__(self, root: Path, height: int, width: int) -> None:
        from mfg_lightning.scene.camera import kitti_like_intrinsics

        self.root, self.height, self.width = Path(root), int(height), int(width)
        self.intrinsics = kitti_like_intrinsics(self.height, self.width)

    @property
    def entries(self) -> list[str]:
        """The top-level names this tree writes under ``root``."""
        return ["sequences", "poses"]

    def write_frame(self, seq: Sequence, world: Any, k: int, frame: Any) -> None:
        """Frame ``k`` of ``seq``, rendered (``frame``: a ``RenderedFrame``)."""
        from mfg_lightning.flow import io as flow_io

        path = self.root / "sequences" / seq.name / "image_2" / f"{k:06d}.png"
        flow_io.write_rgb(path, frame.rgb.permute(1, 2, 0).numpy())

    def write_sequence(self, seq: Sequence) -> None:
        """The per-sequence files, after its frames (so a sequence with poses is complete)."""
        from mfg_lightning.data.kitti import write_kitti_calib
        from mfg_lightning.trajectory import pose_io

        folder = self.root / "sequences" / seq.name
        write_kitti_calib(folder / "calib.txt", self.intrinsics.numpy())
        pose_io.write_kitti_times(folder / "times.txt", np.arange(len(seq.poses)) / FRAME_RATE_HZ)
        pose_io.write_kitti_poses(self.root / "poses" / f"{seq.name}.txt", seq.relative_to_first)


class VkittiTree:
    """Writes Virtual KITTI 1.3.1 (``version=1``) or 2.0.3 (``version=2``): RGB, depth, forward
    flow, extrinsics (and 2.0.3's intrinsics), variation ``clone``, in the paths the reader
    (:mod:`mfg_lightning.data.vkitti`) reads."""

    layout = "vkitti"

    def __init__(self, root: Path, height: int, width: int, version: int) -> None:
        from mfg_lightning.data.vkitti import VKITTI1_INTRINSICS
        from mfg_lightning.data.vkitti_files import VkittiLayout

        self.root, self.height, self.width = Path(root), int(height), int(width)
        self.version = int(version)
        if self.version == 1 and (self.height, self.width) != VKITTI_SIZE:
            raise ValueError(
                f"height={height} width={width}: Virtual KITTI 1.3.1 (version=1) has one camera, "
                f"{VKITTI_SIZE[1]} × {VKITTI_SIZE[0]} with fx = 725, and ships no intrinsics; "
                "use version=2 (2.0.3, with its intrinsic.txt) for other sizes"
            )
        self.paths = VkittiLayout(self.root, self.version)
        self.intrinsics = geometry.scale_intrinsics(
            torch.tensor(VKITTI1_INTRINSICS, dtype=torch.float64),
            self.width / VKITTI_SIZE[1],
            self.height / VKITTI_SIZE[0],
        )

    @property
    def entries(self) -> list[str]:
        return [d.name for d in self.paths.top_dirs()]

    def write_frame(self, seq: Sequence, world: Any, k: int, frame: Any) -> None:
        from mfg_lightning.flow import io as flow_io
        from mfg_lightning.scene.render import FAR_PLANE, exact_flow

        P = self.paths
        flow_io.write_rgb(P.file("rgb", seq.name, VARIATION, k), frame.rgb.permute(1, 2, 0).numpy())
        depth = frame.depth.numpy()
        flow_io.write_vkitti_depth(P.file("depth", seq.name, VARIATION, k), depth)
        if k + 1 >= len(seq.poses):
            return  # the last frame has no successor: no forward flow (2.0.3 ships none)
        exact = exact_flow(world, k, k + 1, self.intrinsics, self.height, self.width, source=frame)
        flow = exact["flow"].permute(1, 2, 0).numpy()
        # Virtual KITTI's encoding spans ±(W − 1), ±(H − 1); the sky has no flow (B = 0)
        in_range = (np.abs(flow) <= np.array([self.width - 1, self.height - 1])).all(axis=2)
        valid = exact["flow_valid"].numpy() & (depth < FAR_PLANE) & in_range
        flow_io.write_vkitti_flow_png(P.file("flow", seq.name, VARIATION, k), flow, valid)

    def write_sequence(self, seq: Sequence) -> None:
        from mfg_lightning.data.vkitti_files import write_vkitti_extrinsics, write_vkitti_intrinsics

        T_cam_world = geometry.invert_pose(torch.from_numpy(seq.relative_to_first)).numpy()
        write_vkitti_extrinsics(
            self.paths.extrinsics_file(seq.name, VARIATION), T_cam_world, self.version
        )
        intrinsics_file = self.paths.intrinsics_file(seq.name, VARIATION)
        if intrinsics_file is not None:
            K = np.repeat(self.intrinsics.numpy()[None], len(seq.poses), axis=0)
            write_vkitti_intrinsics(intrinsics_file, K)


# --------------------------------------------------------------------------------------------
# The output directory
# --------------------------------------------------------------------------------------------


def _prepare_out(out: Path, overwrite: bool) -> None:
    """Refuse a non-empty ``out`` unless ``overwrite`` and it holds a previous export, whose
    entries (and only those) are then removed."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"out={out} is a file, not a directory")
    if not out.exists() or not any(out.iterdir()):
        return
    manifest = out / MANIFEST
    if not overwrite:
        raise ValueError(
            f"out={out} is not empty: choose an empty or new directory, or pass overwrite=true "
            "to replace a previous export there"
        )
    if not manifest.is_file():
        raise ValueError(
            f"out={out} is not empty and holds no previous export ({MANIFEST} is missing): "
            "overwrite=true only replaces an export; choose an empty or new directory"
        )
    try:
        previous = json.loads(manifest.read_text())
        entries = [str(e) for e in previous["entries"]]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{manifest}: not a readable export manifest ({err})") from None
    for entry in entries:
        target = out / entry
        if Path(entry).name != entry or entry in ("", ".", ".."):
            raise ValueError(f"{manifest}: entry {entry!r} is not a name inside out={out}")
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
    manifest.unlink()


def _write_manifest(
    tree: KittiTree | VkittiTree, sequences: list[Sequence], cfg: DictConfig, complete: bool
) -> None:
    from mfg_lightning.core.atomic import atomic_write_text

    manifest = {
        "format": _MANIFEST_FORMAT,
        "tool": "mfg_lightning.data.export",
        "complete": complete,
        "layout": tree.layout,
        "version": tree.version,
        "size": [tree.height, tree.width],
        "intrinsics": [float(v) for v in tree.intrinsics],
        "entries": tree.entries,
        "sequences": {
            s.name: {"world": s.world, "seed": s.seed, "frames": len(s.poses)} for s in sequences
        },
        "dataset": OmegaConf.to_container(cfg.dataset, resolve=True),
    }
    atomic_write_text(tree.root / MANIFEST, json.dumps(manifest, indent=2, default=str) + "\n")


def _image_size(cfg: DictConfig) -> tuple[int, int]:
    from mfg_lightning.scene.render import check_render_size

    height, width = cfg.get("height"), cfg.get("width")
    try:
        check_render_size(height, width)
    except ValueError as err:
        raise ValueError(f"height={height}, width={width}: {err}") from None
    return int(height), int(width)


def export(cfg: DictConfig, progress: bool = True) -> dict[str, Any]:
    """Write the tree ``cfg`` describes (``conf/export.yaml``); return its manifest.

    Raises:
        ValueError: a bad setting (named) or an ``out`` that may not be written.
    """
    from hydra.utils import get_class, instantiate
    from tqdm.auto import tqdm

    from mfg_lightning.data.rendered_worlds import crossing_config, generate_world, world_config
    from mfg_lightning.data.synthetic import SyntheticDataModule
    from mfg_lightning.data.vkitti_files import normalize_version
    from mfg_lightning.scene.render import render_frame

    layout = cfg.get("layout")
    if layout not in LAYOUTS:
        raise ValueError(f"layout={layout}: one of {', '.join(LAYOUTS)}")
    if cfg.get("out") in (None, "", "???"):
        raise ValueError("out is not set: the directory to write the tree into, e.g. out=/data/x")
    target = cfg.dataset.get("_target_")
    if target is None or not issubclass(get_class(target), SyntheticDataModule):
        raise ValueError(
            f"dataset={target}: the export writes the synthetic worlds (dataset=synthetic)"
        )
    height, width = _image_size(cfg)
    out = Path(str(cfg.out)).expanduser().absolute()
    if layout == "kitti":
        tree: KittiTree | VkittiTree = KittiTree(out, height, width)
    else:
        try:
            version = normalize_version(cfg.get("version"))
        except ValueError:
            raise ValueError(
                f"version={cfg.get('version')}: 1 (Virtual KITTI 1.3.1) or 2 (2.0.3)"
            ) from None
        tree = VkittiTree(out, height, width, version)
    # Each frame is rendered once here: a sample cache would only write what is never read.
    datamodule = instantiate(
        cfg.dataset, flow={"source": "exact"}, sample_cache={"memory_mb": 0, "disk": False}
    )
    sequences = synthetic_sequences(datamodule, layout)
    worlds_config = world_config(datamodule.world)
    crossing = crossing_config(datamodule.world)

    _prepare_out(out, bool(cfg.get("overwrite")))
    out.mkdir(parents=True, exist_ok=True)
    _write_manifest(tree, sequences, cfg, complete=False)
    total = sum(len(s.poses) for s in sequences)
    name = f"{layout} {tree.version}" if tree.version else layout
    bar = tqdm(total=total, desc=f"export {name}", unit="frame", disable=not progress)
    start = time.perf_counter()
    try:
        for seq in sequences:
            world = generate_world(seq.poses, seq.seed, seq.world, worlds_config, crossing)
            for k in range(len(seq.poses)):
                frame = render_frame(world, k, tree.intrinsics, height, width)
                tree.write_frame(seq, world, k, frame)
                bar.update(1)
            tree.write_sequence(seq)
    finally:
        bar.close()
    seconds = time.perf_counter() - start
    _write_manifest(tree, sequences, cfg, complete=True)
    log.info(
        "wrote %d frames of %d sequences (%s) at %d × %d to %s in %.1f s (%.3f s per frame)",
        total, len(sequences), " ".join(s.name for s in sequences), width, height, out,
        seconds, seconds / max(total, 1),
    )  # fmt: skip
    return json.loads((out / MANIFEST).read_text())


@exit_on_unknown_choice
@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="export")
@exit_on_user_error
def main(cfg: DictConfig) -> None:
    try:
        manifest = export(cfg)
    except KeyboardInterrupt:
        import sys

        print(
            f"interrupted: the files in {cfg.out} are whole but the tree is not complete "
            f"({MANIFEST} says so); run again with overwrite=true",
            file=sys.stderr,
        )
        sys.exit(130)
    print(f"{cfg.out}: {manifest['layout']} tree, sequences {' '.join(manifest['sequences'])}")


if __name__ == "__main__":
    main()
