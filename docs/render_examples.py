"""Write example picture grids of rendered worlds (the ones in ``docs/img/``).

``python docs/render_examples.py --out docs/img [--poses
../shared/data/kitti_odometry/poses/00.txt]``
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from mfg_lightning.pictures.rendered_frames import frame_panels, picture_grid
from mfg_lightning.scene.render import check_render_size, exact_flow, render_frame
from mfg_lightning.scene.seeding import seeded_rng
from mfg_lightning.scene.worlds import World


def main(argv: Sequence[str] | None = None) -> int:
    """Write example picture grids of rendered worlds (the ones in ``docs/img/``).

    ``python docs/render_examples.py --out docs/img [--poses .../poses/00.txt]``: a grid of
    four frames of a procedural trajectory's world, the same of a KITTI trajectory's world when
    ``--poses`` is given, and one frame at KITTI's full 1241 × 376.
    """
    import argparse
    from pathlib import Path

    from mfg_lightning.core.errors import exit_on_user_error
    from mfg_lightning.pictures.grids import save_png
    from mfg_lightning.trajectory.pose_io import read_kitti_poses

    parser = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the PNGs")
    parser.add_argument("--poses", type=Path, help="a KITTI poses/XX.txt file")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--height", type=int, default=192)
    parser.add_argument("--width", type=int, default=512)
    args = parser.parse_args(argv)

    @exit_on_user_error
    def run() -> int:
        from mfg_lightning.scene.camera import kitti_like_intrinsics, procedural_trajectory

        check_render_size(args.height, args.width)
        trajectories = [
            ("procedural", procedural_trajectory(seeded_rng(args.seed, "trajectory", "demo"), 400))
        ]
        if args.poses is not None:
            if not args.poses.is_file():
                raise FileNotFoundError(f"--poses: no such file: {args.poses}")
            trajectories.append((args.poses.stem, torch.from_numpy(read_kitti_poses(args.poses))))
        K = kitti_like_intrinsics(args.height, args.width)
        for name, poses in trajectories:
            world = World.generate(poses, args.seed, name)
            picks = np.linspace(0, world.num_frames - 2, 6).round().astype(int)[1:-1]
            columns, headers = [], []
            for k in picks:
                frame = render_frame(world, int(k), K, args.height, args.width)
                flow = exact_flow(world, int(k), int(k) + 1, K, args.height, args.width, frame)
                columns.append(frame_panels(frame, flow))
                headers.append(f"{name} {k}→{k + 1}")
            path = save_png(picture_grid(columns, headers), args.out / f"rendered_{name}.png")
            print(path)
        world = World.generate(trajectories[-1][1], args.seed, trajectories[-1][0])
        k = world.num_frames // 3
        h, w = 376, 1241
        frame = render_frame(world, k, kitti_like_intrinsics(h, w), h, w)
        path = args.out / f"rendered_{trajectories[-1][0]}_{w}x{h}.png"
        print(save_png(frame.rgb.permute(1, 2, 0).numpy(), path))
        return 0

    return run()


if __name__ == "__main__":
    raise SystemExit(main())
