"""OpenCV's contrib build: one ``cv2`` with DIS and the contrib modules' flow algorithms, and the
install step that replaces a plain OpenCV wheel by it (``bench/install_opencv.py``)."""

from __future__ import annotations

import cv2

from conftest import bench_module

install_opencv = bench_module("install_opencv")


def test_cv2_has_dis_and_the_contrib_flow_algorithms_from_the_contrib_package_alone() -> None:
    assert hasattr(cv2, "DISOpticalFlow_create")
    for factory in ("createOptFlow_DeepFlow", "createOptFlow_DualTVL1", "createOptFlow_PCAFlow",
                    "createOptFlow_Farneback", "createOptFlow_SparseToDense",
                    "createOptFlow_DenseRLOF"):  # fmt: skip
        assert hasattr(cv2.optflow, factory), factory
    assert install_opencv.installed(install_opencv.CONTRIB) is not None
    plain = [n for n in install_opencv.PLAIN if install_opencv.installed(n)]
    assert not plain, f"{plain} installed beside {install_opencv.CONTRIB}: one cv2, two owners"


def test_the_install_step_removes_a_plain_wheel_and_mends_a_contrib_one_beside_it() -> None:
    plan, contrib = install_opencv.plan, install_opencv.CONTRIB
    assert plan({contrib: "5.1.0.95"}, "py") == []  # nothing to do
    assert plan({"opencv-python-headless": "4.10.0.84"}, "py") == [
        ["py", "-m", "pip", "uninstall", "-y", "opencv-python-headless"]
    ]  # the project's install then brings the contrib build
    both = {"opencv-python": "4.9.0", "opencv-python-headless": "5.1.0.95", contrib: "5.1.0.95"}
    assert plan(both, "py") == [
        ["py", "-m", "pip", "uninstall", "-y", "opencv-python-headless", "opencv-python"],
        ["py", "-m", "pip", "install", "--force-reinstall", "--no-deps", f"{contrib}==5.1.0.95"],
    ]
