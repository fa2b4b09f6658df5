"""The ``flow`` config group: what each option builds, defaults per dataset, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate

from conftest import run_module
from fake_datasets import make_kitti, tree_snapshot
from mfg_lightning.core.config import compose
from mfg_lightning.data.kitti import KittiDataModule
from mfg_lightning.data.synthetic import SyntheticDataModule
from mfg_lightning.data.vkitti import VirtualKittiDataModule
from mfg_lightning.flow.estimators import (
    DISFlowEstimator,
    EstimatedFlow,
    ExactFlow,
    FlowFiles,
    GroundTruthFlow,
    parse_flow,
)


def test_each_dataset_gets_its_default_and_the_override_wins(tmp_path: Path) -> None:
    cfg = compose("train", [f"paths.cache_dir={tmp_path}"])
    assert cfg.flow.source == "exact" and cfg.dataset.flow == cfg.flow
    assert (cfg.flow.noise_std, cfg.flow.outlier_fraction) == (0.3, 0.01)
    kitti = compose("train", ["dataset=kitti"])
    assert kitti.flow.source == "dis" and kitti.dataset.flow.preset == "medium"
    assert compose("train", ["experiment=paper_kitti"]).dataset.flow.source == "dis"
    files = compose("train", ["dataset=kitti", "flow=files", "flow.dir=/x"]).dataset.flow
    assert dict(files) == {"source": "files", "dir": "/x"}
    dis = compose("train", ["flow=dis", "flow.height=96", "flow.width=256"]).dataset.flow
    assert (dis.source, dis.height, dis.width) == ("dis", 96, 256)
    # evaluate composes a dataset the same way when one is given
    assert compose("evaluate", ["ckpt_path=x", "dataset=kitti"]).dataset.flow.source == "dis"
    assert compose("evaluate", ["ckpt_path=x", "dataset=synthetic"]).dataset.flow.source == "exact"


def test_parse_flow_builds_the_source_and_names_bad_keys() -> None:
    exact = parse_flow(None, default="exact")
    assert exact == ExactFlow(0.3, 0.01)
    dis = parse_flow({"source": "dis", "preset": "fast", "height": 96, "width": 256}, "exact")
    assert isinstance(dis, EstimatedFlow) and isinstance(dis.estimator, DISFlowEstimator)
    assert dis.image_hw((1, 1)) == (96, 256) and dis.key()["preset"] == "fast"
    assert parse_flow({"source": "dis"}, "exact").image_hw((192, 512)) == (192, 512)
    assert parse_flow({"source": "files", "dir": "/f"}, "dis") == FlowFiles("/f")
    bad = {
        "flow.source='raft2'": {"source": "raft2"},
        "flow.bogus": {"source": "dis", "bogus": 1},
        "flow.preset for flow.source=exact": {"source": "exact", "preset": "fast"},
        "flow.preset must be one of": {"source": "dis", "preset": "slow"},
        "flow.params": {"source": "dis", "params": {"nope": 1}},
        "flow.height and flow.width": {"source": "dis", "height": 96},
        "flow.width must be a positive": {"source": "dis", "height": 96, "width": 0},
        "flow.noise_std": {"source": "exact", "noise_std": -1.0},
        "flow.outlier_fraction": {"source": "exact", "outlier_fraction": 2.0},
        "flow.dir": {"source": "files", "dir": "???"},
    }
    for message, cfg in bad.items():
        with pytest.raises(ValueError, match=message.replace("(", r"\(")):
            parse_flow(cfg, "exact")


def test_each_dataset_refuses_the_source_it_cannot_give(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="flow.source=exact: dataset=kitti has no exact flow"):
        KittiDataModule(str(tmp_path), flow={"source": "exact"})
    with pytest.raises(ValueError, match="flow.source=files: dataset=synthetic"):
        SyntheticDataModule(flow={"source": "files", "dir": str(tmp_path)})
    # ground_truth is the flow a dataset ships: Virtual KITTI's, not KITTI odometry's or synthetic
    with pytest.raises(ValueError, match="flow.source=ground_truth: dataset=kitti has no ground"):
        KittiDataModule(str(tmp_path), flow={"source": "ground_truth"})
    with pytest.raises(ValueError, match="flow.source=ground_truth: dataset=synthetic"):
        SyntheticDataModule(flow={"source": "ground_truth"})
    with pytest.raises(ValueError, match="flow.source=dis: dataset=vkitti"):
        VirtualKittiDataModule(str(tmp_path), flow={"source": "dis"})
    assert isinstance(VirtualKittiDataModule(str(tmp_path)).flow, GroundTruthFlow)
    # a render size below the model input cannot be resized down to it
    with pytest.raises(ValueError, match=r"flow.height=32: the render size 32 × 512"):
        SyntheticDataModule(flow={"source": "dis", "height": 32, "width": 512})


def test_the_exact_source_is_the_default_and_builds_what_it_did(tmp_path: Path) -> None:
    """flow=exact keeps today's generator: the default config renders no flow and caches only
    the samples it generated (``synthetic_samples``), never estimated flow."""
    cfg = compose("train", [f"paths.cache_dir={tmp_path / 'cache'}", "paths.output_dir=x"])
    dm = instantiate(cfg.dataset)
    explicit = SyntheticDataModule(flow={"source": "exact", "noise_std": 0.3})
    a, b = dm.dataset("train")[5], explicit.dataset("train")[5]
    assert all(np.array_equal(a[k], b[k]) for k in ("flow", "flow_valid", "depth", "rgb"))
    dm.prepare_data()
    cache = tmp_path / "cache"
    written = {p.name for p in cache.iterdir()} if cache.exists() else set()
    assert written <= {"synthetic_samples"}


def test_kitti_flow_settings_reach_the_dataset(tmp_path: Path) -> None:
    fake = make_kitti(tmp_path / "kitti", sequences=("09",), n_frames=4)
    dm = KittiDataModule(
        str(fake.root), test_sequences=["09"], train_sequences=["00"], cache_dir=str(tmp_path),
        flow={"source": "dis", "preset": "ultrafast", "height": 32, "width": 100},
    )  # fmt: skip
    ds = dm.build_dataset("test")
    assert ds.estimator.preset == "ultrafast" and ds.compute_hw == (32, 100)
    assert ds.cache_path(0).parent.name == "09@32x100"


@pytest.mark.slow
def test_bad_flow_settings_exit_2_with_one_line_and_write_no_data(tmp_path: Path) -> None:
    fake = make_kitti(tmp_path / "kitti", sequences=("00", "09"), n_frames=4)
    before = tree_snapshot(fake.root)
    cases = {
        "flow.source": ["flow.source=sift"],
        "flow.height": ["flow=dis", "flow.height=16", "flow.width=512"],
        "flow.preset": ["dataset=kitti", f"dataset.data_root={fake.root}", "flow.preset=slow"],
        "flow.source=exact": ["dataset=kitti", f"dataset.data_root={fake.root}", "flow=exact"],
        "flow=sift": ["flow=sift"],
    }
    for key, args in cases.items():
        proc = run_module(
            "mfg_lightning.train", *args, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
            check=False,
        )  # fmt: skip
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
        assert proc.returncode == 2, (key, proc.stderr[-2000:])
        assert len(errors) == 1 and key in errors[0], (key, proc.stderr[-2000:])
    assert tree_snapshot(fake.root) == before
    assert not (tmp_path / "cache").exists()  # no flow cache either
