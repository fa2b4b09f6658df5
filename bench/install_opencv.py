"""Make room for OpenCV's contrib build before the project is installed (``make install``,
``make install-gpu``).

The project depends on ``opencv-contrib-python-headless``: DIS and the contrib modules' dense flow
algorithms (``cv2.optflow``: DeepFlow, TV-L1, PCA-Flow, ...). OpenCV's plain wheels
(``opencv-python-headless``, ``opencv-python``) install the same ``cv2`` package: pip lets two of
them be installed at once, the later one's files overwrite the earlier one's, and uninstalling
either then breaks the other. So, where a plain wheel is installed:

1. it is uninstalled;
2. a contrib build installed beside it is reinstalled at its version (its files were just
   removed); else the project's install that follows brings one.

Nothing is done where no plain wheel is installed. ``--dry-run`` prints the commands only.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import shlex
import subprocess
import sys

#: OpenCV's wheels without the contrib modules (the same ``cv2`` package)
PLAIN = ("opencv-python-headless", "opencv-python")
#: the build the project depends on
CONTRIB = "opencv-contrib-python-headless"


def installed(name: str) -> str | None:
    """The installed version of distribution ``name``, or None."""
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def plan(versions: dict[str, str | None], python: str) -> list[list[str]]:
    """The pip commands that leave no plain OpenCV wheel and an intact contrib one (if any).

    Args:
        versions: distribution name → installed version (None: not installed), for
            :data:`PLAIN` and :data:`CONTRIB`.
        python: the interpreter whose pip runs.
    """
    plain = [name for name in PLAIN if versions.get(name)]
    if not plain:
        return []
    commands = [[python, "-m", "pip", "uninstall", "-y", *plain]]
    contrib = versions.get(CONTRIB)
    if contrib:
        commands.append([python, "-m", "pip", "install", "--force-reinstall", "--no-deps",
                         f"{CONTRIB}=={contrib}"])  # fmt: skip
    return commands


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = p.parse_args(argv)
    versions = {name: installed(name) for name in (*PLAIN, CONTRIB)}
    commands = plan(versions, sys.executable)
    if not commands:
        return 0
    found = ", ".join(f"{n} {v}" for n, v in versions.items() if v)
    print(f"install-opencv: {found} installed; the project needs {CONTRIB} alone", flush=True)
    for command in commands:
        print("install-opencv: " + shlex.join(command), flush=True)
        if not args.dry_run and subprocess.run(command, check=False).returncode:
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
