"""A GPU user's install, tested on a CPU without a network: ``make install`` and ``make
install-gpu`` through a stand-in Python that records its arguments, ``bench/install_gpu.py``'s
plan and advice, and pip's choices by ``pip install --dry-run`` on a folder of stand-in wheels
(metadata only), with none of this machine's pip settings."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import pytest
import torch

from conftest import REPO, bench_module, run_make

install_gpu = bench_module("install_gpu")


def test_make_install_hands_a_torch_spec_with_options_to_pip_as_separate_arguments(
    tmp_path: Path,
) -> None:
    """``TORCH_SPEC="torch==2.5.1 --index-url <URL>"``: pip used to get it as one argument
    (``Invalid requirement``). A stand-in Python records each call's arguments and has no
    torch, so the install branch runs."""
    calls = tmp_path / "calls"
    fake = tmp_path / "python"
    fake.write_text(
        "#!/bin/sh\n"
        f"printf '%s\\n' \"$@\" >> {shlex.quote(str(calls))}\n"
        f"echo '<end>' >> {shlex.quote(str(calls))}\n"
        'if [ "$1" = "-c" ]; then exit 1; fi\n'  # `import torch` fails
    )
    fake.chmod(0o755)
    spec = "torch==2.5.1 --index-url https://example.invalid/whl/cu121"
    proc = run_make("install", f"PYTHON={fake}", f"TORCH_SPEC={spec}")
    assert proc.returncode == 0, proc.stderr
    argv = [c.strip("\n").split("\n") for c in calls.read_text().split("<end>\n") if c]
    assert argv[0] == ["-c", "import torch"]
    assert argv[1] == ["-m", "pip", "install", *spec.split()]
    assert argv[2] == ["bench/install_opencv.py"]  # a plain OpenCV wheel out of the way
    assert argv[3] == ["-m", "pip", "install", "-e", ".[dev]"]  # the CPU set-up as before


def test_make_install_gpu_hands_its_spec_to_the_installer_whole() -> None:
    spec = "torch===2.5.1+cu121 --index-url https://example.invalid/whl/cu121"
    proc = run_make("-n", "install-gpu", f"TORCH_GPU_SPEC={spec}")
    assert proc.returncode == 0, proc.stderr
    argv = shlex.split(proc.stdout.strip().splitlines()[-1])
    assert argv[1:] == ["bench/install_gpu.py", "--torch-spec", spec, "--extras", ""]
    commands, _ = install_gpu.plan(install_gpu.Torch("2.13.0+cpu", None), spec, "python")
    assert commands[0] == ["python", "-m", "pip", "install", *spec.split()]
    # The default is an exact pin, and no dev extras are installed.
    default = run_make("-n", "install-gpu").stdout
    assert f"--torch-spec '{install_gpu.DEFAULT_SPEC}'" in default
    assert install_gpu.DEFAULT_SPEC.startswith("torch===")
    assert all("[dev]" not in " ".join(c) for c in commands)


def test_install_gpu_adds_the_sweeps_extra_when_asked() -> None:
    proc = run_make("-n", "install-gpu", "GPU_EXTRAS=sweeps")
    assert shlex.split(proc.stdout.strip().splitlines()[-1])[-2:] == ["--extras", "sweeps"]
    cuda = install_gpu.Torch("2.5.1+cu121", "12.1", True, 1)
    # installed already and torch kept: nothing to do, unless an extra is asked for
    assert install_gpu.plan(cuda, python="py", project_installed=True)[0] == []
    commands, _ = install_gpu.plan(cuda, python="py", project_installed=True, extras="sweeps")
    assert commands == [["py", "-m", "pip", "install", "-e", f"{install_gpu.REPO}[sweeps]"]]
    with pytest.raises(ValueError, match="extras"):
        install_gpu.plan(cuda, python="py", extras="sweeps; rm")


@pytest.mark.parametrize(
    ("torch_info", "kept"),
    [
        (install_gpu.Torch("2.5.1+cu121", "12.1", True, 1), True),
        (install_gpu.Torch("2.4.0", "12.4", False, 0), True),  # kept; the check then advises
        (install_gpu.Torch("2.13.0+cpu", None), False),
        (install_gpu.Torch("2.3.1+cu121", "12.1", True, 1), False),  # pip would replace it
        (None, False),
    ],
)
def test_install_gpu_keeps_a_cuda_torch_from_2_4_on_and_installs_one_otherwise(
    torch_info: Any, kept: bool
) -> None:
    commands, why = install_gpu.plan(torch_info, python="py", project_installed=True)
    torch_install = [c for c in commands if "-e" not in c]
    assert (not torch_install) == kept, why
    if not kept:
        assert torch_install == [["py", "-m", "pip", "install", install_gpu.DEFAULT_SPEC]]
        assert commands[-1] == ["py", "-m", "pip", "install", "-e", str(REPO)]
    else:
        assert commands == []  # this checkout is installed and torch kept: no pip at all
    assert install_gpu.release("2.10.0a0+git") == (2, 10, 0)


def test_install_gpu_says_what_to_do_when_cuda_is_not_available() -> None:
    cpu = install_gpu.advice(install_gpu.Torch("2.13.0+cpu", None))
    assert "CPU-only build" in cpu and "TORCH_GPU_SPEC" in cpu
    no_gpu = install_gpu.advice(install_gpu.Torch("2.13.0", "12.8", False, 0))
    assert "nvidia-smi" in no_gpu and "12.8" in no_gpu and "--gpus all" in no_gpu


def _wheel(folder: Path, version: str) -> None:
    """A stand-in torch wheel: the metadata pip reads to resolve, nothing else."""
    name = f"torch-{version}-py3-none-any.whl"
    info = f"torch-{version}.dist-info"
    with zipfile.ZipFile(folder / name, "w") as z:
        z.writestr(f"{info}/METADATA", f"Metadata-Version: 2.1\nName: torch\nVersion: {version}\n")
        z.writestr(
            f"{info}/WHEEL", "Wheel-Version: 1.0\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
        )
        z.writestr(f"{info}/RECORD", "")


#: The first pip with ``install --dry-run`` and ``--report`` (22.2).
PIP_WITH_DRY_RUN = (22, 2)


def _pip_cannot_dry_run() -> str | None:
    """Why this interpreter's pip cannot answer a dry run (no pip, or one older than
    ``--dry-run --report``): causes outside the project; None when it can."""
    import importlib.metadata

    try:
        version = importlib.metadata.version("pip")
    except importlib.metadata.PackageNotFoundError:
        return f"no pip in {sys.executable}"
    parts = tuple(int(p) for p in version.split(".")[:2] if p.isdigit())
    if parts < PIP_WITH_DRY_RUN:
        return f"pip {version} has no install --dry-run --report (pip 22.2 and later)"
    return None


def _pip_dry_run(links: Path, report: Path, *requirement: str, ignore_installed: bool = True):
    """What ``pip install`` would install from ``links`` alone: (returncode, [versions])."""
    command = [sys.executable, "-m", "pip", "install", "--dry-run", "--no-deps",
               "--no-index", "--find-links", str(links), "--report", str(report), "--quiet",
               *(["--ignore-installed"] if ignore_installed else []), *requirement]  # fmt: skip
    # None of this machine's pip settings (find-links, indexes, constraints): the folder alone.
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env["PIP_CONFIG_FILE"] = os.devnull
    proc = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    if proc.returncode:
        return proc.returncode, proc.stderr
    installs = json.loads(report.read_text()).get("install", [])
    return 0, [i["metadata"]["version"] for i in installs]


def test_pip_dry_run_the_gpu_spec_refuses_a_cpu_build_and_an_installed_torch_is_kept(
    tmp_path: Path,
) -> None:
    both, cpu_only = tmp_path / "both", tmp_path / "cpu_only"
    for folder, versions in (
        (both, ("2.13.0", "2.13.0+cpu", "2.14.1")),
        (cpu_only, ("2.13.0+cpu",)),
    ):
        folder.mkdir()
        for version in versions:
            _wheel(folder, version)
    report = tmp_path / "report.json"
    reason = _pip_cannot_dry_run()
    if reason is not None:  # the environment, not the project: say which
        pytest.skip(reason)
    # Any other failure is the regression this test guards (a spec pip refuses or cannot meet).
    code, chosen = _pip_dry_run(both, report, install_gpu.DEFAULT_SPEC)
    assert code == 0, f"pip could not resolve {install_gpu.DEFAULT_SPEC}: {str(chosen)[-800:]}"
    assert chosen == ["2.13.0"]  # the release, not the local +cpu build
    # `==` takes the +cpu build where a find-links folder offers it: why the GPU route pins ===.
    assert _pip_dry_run(both, report, "torch==2.13.0") == (0, ["2.13.0+cpu"])
    code, err = _pip_dry_run(cpu_only, report, install_gpu.DEFAULT_SPEC)
    assert code != 0 and "No matching distribution" in err  # refused, not taken
    # The project's own `torch>=2.4` keeps the installed torch (a CUDA one on a GPU machine)
    # though the folder offers a newer one: `pip install -e .` never replaces it.
    installed = torch.__version__
    assert install_gpu.release(installed) >= install_gpu.MIN_TORCH
    assert _pip_dry_run(both, report, "torch>=2.4", ignore_installed=False) == (0, [])
