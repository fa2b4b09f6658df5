"""Install mfg-lightning for a CUDA GPU: ``make install-gpu`` (docs/gpu.md).

What it does, in order:

1. Asks the Python that runs it which torch it has (in a subprocess: torch may be missing).
2. Keeps that torch when it is a CUDA build of at least :data:`MIN_TORCH` (the project's
   ``torch>=2.4``, so that step 3 does not replace it). Otherwise installs ``--torch-spec``
   (default :data:`DEFAULT_SPEC`): an exact ``===`` pin, because ``torch==2.13.0`` also matches
   local builds such as ``2.13.0+cpu``, which pip prefers where a find-links folder offers one;
   ``===`` matches the version string exactly and never takes a ``+cpu`` build. The spec is
   split like a shell line, so ``"torch===2.5.1+cu121 --index-url <URL>"`` reaches pip as three
   arguments.
3. Installs the project itself, editable, without the ``[dev]`` extras (wandb, mlflow, optuna,
   evo, Jupyter: the GPU check and training need none of them), with the extras ``--extras``
   names (``sweeps`` for Hydra's SLURM, joblib and Optuna plugins on a cluster:
   ``make install-gpu GPU_EXTRAS=sweeps``). Skipped when this checkout is already what
   ``import mfg_lightning`` finds, torch was kept and no extra is asked for: a re-run needs no
   index.
4. Checks ``torch.cuda.is_available()`` and, when it is False, says why it may be and what to do
   (exit status 1).

``--dry-run`` prints the plan and runs each pip command with ``--dry-run`` (pip resolves and
reports what it would install, installs nothing), and skips step 4. Standard library only: it
runs before torch is there.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: The oldest torch kept: pyproject.toml's ``torch>=2.4`` (fused Adam on the CPU); an older one
#: would be replaced by pip in step 3 anyway, by whatever torch the index has.
MIN_TORCH = (2, 4)
#: The torch installed where none is kept: the CPU set-up's version (Makefile ``TORCH_SPEC``),
#: pinned with ``===`` so that only the release itself matches (on Linux x86-64 the index's
#: build of it is the CUDA one).
DEFAULT_SPEC = "torch===2.13.0"

PROBE = """
import json
try:
    import torch
except Exception as err:
    print(json.dumps(None))
else:
    print(json.dumps({"version": torch.__version__, "cuda": torch.version.cuda,
                      "available": torch.cuda.is_available(),
                      "devices": torch.cuda.device_count()}))
"""


@dataclass(frozen=True)
class Torch:
    """What an installed torch says of itself."""

    version: str
    cuda: str | None
    available: bool = False
    devices: int = 0


def release(version: str) -> tuple[int, ...]:
    """``"2.5.1+cu121"`` → ``(2, 5, 1)``: the release numbers, local and pre-release tags off."""
    match = re.match(r"\d+(\.\d+)*", version)
    return tuple(int(x) for x in match.group(0).split(".")) if match else ()


def probe(python: str = sys.executable) -> Torch | None:
    """The torch of ``python``, or None when it has none that imports."""
    out = subprocess.run([python, "-c", PROBE], capture_output=True, text=True, check=False)
    try:
        info = json.loads(out.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        return None
    return None if info is None else Torch(**info)


def keeps(torch: Torch | None) -> tuple[bool, str]:
    """Whether the installed torch is kept, and why, in words."""
    if torch is None:
        return False, "no torch installed"
    if not torch.cuda:
        return False, f"torch {torch.version} is a CPU-only build"
    if release(torch.version) < MIN_TORCH:
        need = ".".join(map(str, MIN_TORCH))
        return False, f"torch {torch.version} is older than {need} (pyproject.toml)"
    return True, f"torch {torch.version} (CUDA {torch.cuda}) kept"


def installed_here(python: str = sys.executable) -> bool:
    """Whether ``import mfg_lightning`` finds this checkout's sources."""
    code = "import mfg_lightning, os; print(os.path.realpath(mfg_lightning.__file__))"
    out = subprocess.run([python, "-c", code], capture_output=True, text=True, check=False)
    return out.returncode == 0 and out.stdout.strip().startswith(str(REPO / "src"))


def plan(
    torch: Torch | None,
    spec: str = DEFAULT_SPEC,
    python: str = sys.executable,
    pip_args: str = "",
    project_installed: bool = False,
    extras: str = "",
) -> tuple[list[list[str]], str]:
    """The pip commands to run, and why torch is kept or installed.

    Args:
        torch: the installed torch (:func:`probe`).
        spec: the torch to install when the installed one is not kept, split like a shell line
            (a requirement and pip options such as ``--index-url``).
        python: the interpreter whose pip installs.
        pip_args: more ``pip install`` options for every command, split like a shell line.
        project_installed: this checkout is installed already (:func:`installed_here`).
        extras: the project's optional extras to install with it, comma-separated
            (``"sweeps"``, ``"sweeps,loggers"``; ``pyproject.toml``'s names).
    """
    names = [e.strip() for e in extras.split(",") if e.strip()]
    if any(not e.replace("-", "").replace("_", "").isalnum() for e in names):
        raise ValueError(f"--extras takes names separated by commas, got {extras!r}")
    keep, why = keeps(torch)
    pip = [python, "-m", "pip", "install", *shlex.split(pip_args)]
    commands = [] if keep else [[*pip, *shlex.split(spec)]]
    if not (keep and project_installed and not names):
        target = f"{REPO}[{','.join(names)}]" if names else str(REPO)
        commands.append([*pip, "-e", target])
    return commands, why


def advice(torch: Torch | None) -> str:
    """What to do when CUDA is not available after the install."""
    if torch is None:
        return "torch does not import: see pip's output above"
    spec = "make install-gpu TORCH_GPU_SPEC='torch===<version>+cu<XY> --index-url <URL>'"
    if not torch.cuda:
        return (
            f"torch {torch.version} is a CPU-only build: the package index offered no CUDA build "
            "of the requested version. Name one: the version and the index URL that "
            f"pytorch.org's install selector gives for your CUDA, e.g.\n  {spec}"
        )
    hidden = os.environ.get("CUDA_VISIBLE_DEVICES")
    lines = [
        f"torch {torch.version} is built for CUDA {torch.cuda} but sees no GPU. Check:",
        "  * `nvidia-smi` lists the GPU (if not: the NVIDIA driver is missing, or a container "
        "was started without the GPU: `docker run --gpus all ...`);",
        f"  * nvidia-smi's 'CUDA Version' (the newest CUDA the driver runs) is at least "
        f"{torch.cuda}; if it is older, update the driver or install a torch built for that "
        f"CUDA:\n      {spec}",
    ]
    if hidden is not None:
        lines.append(f"  * CUDA_VISIBLE_DEVICES={hidden!r} hides devices: unset it.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--torch-spec", default=DEFAULT_SPEC, help="torch to install if none is kept")
    p.add_argument("--pip-args", default="", help="more pip install options, one string")
    p.add_argument("--dry-run", action="store_true", help="pip resolves, installs nothing")
    p.add_argument("--extras", default="", help="the project's extras to add, e.g. sweeps")
    args = p.parse_args(argv)
    torch = probe()
    pip_args = f"{args.pip_args} --dry-run" if args.dry_run else args.pip_args
    commands, why = plan(
        torch, args.torch_spec, sys.executable, pip_args, installed_here(), args.extras
    )
    print(f"install-gpu: {why}", flush=True)
    # OpenCV's plain wheel out of the way of the contrib one the project needs (install_opencv.py)
    opencv = [sys.executable, str(REPO / "bench" / "install_opencv.py")]
    if subprocess.run([*opencv, *(["--dry-run"] if args.dry_run else [])], check=False).returncode:
        return 1
    for command in commands:
        print("install-gpu: " + shlex.join(command), flush=True)
        if subprocess.run(command, check=False).returncode:
            return 1
    if not commands:
        print("install-gpu: nothing to install", flush=True)
    if args.dry_run:
        return 0
    torch = probe()
    if torch is None or not torch.available:
        print("install-gpu: torch.cuda.is_available() is False\n" + advice(torch), flush=True)
        return 1
    print(
        f"install-gpu: torch {torch.version}, CUDA {torch.cuda}, {torch.devices} GPU(s) "
        "visible; next: make gpu-check",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
