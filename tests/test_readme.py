"""Every command of the README keeps its words: each Hydra command composes as written.

Commands are read from the README's ``bash`` blocks. A multirun's comma-separated sweep takes its
first value (composing is per job); placeholders such as ``<date>`` or ``...`` stand for values, and
composing checks keys, groups and options, not files. The ones that need no data also run, as
tiny trainings, in test_train, test_rendered_flow, test_loggers and test_sweeps.
"""

from __future__ import annotations

import re
import shlex

import pytest

from conftest import REPO
from mfg_lightning.core.config import compose

#: ``python -m <module>`` → its config (the Hydra entry points).
CONFIGS = {
    "mfg_lightning.train": "train",
    "mfg_lightning.evaluate": "evaluate",
    "mfg_lightning.predict": "predict",
    "mfg_lightning.analyze_basis": "analyze_basis",
    "mfg_lightning.reproduce": "reproduce",
    "mfg_lightning.data.check": "check",
    "mfg_lightning.data.export": "export",
}


def readme_commands() -> list[list[str]]:
    """The ``python -m mfg_lightning…`` commands of the README, as argv lists (``mfg-eval-poses``,
    an argparse command, is tested in test_evaluate_poses)."""
    text = (REPO / "README.md").read_text()
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            # a placeholder (<date>, <run dir>) stands for a value the user fills in
            argv = shlex.split(re.sub(r"<[^<>]+>", "PLACEHOLDER", line), comments=True)
            if argv[:2] == ["python", "-m"] and argv[2].startswith("mfg_lightning"):
                commands.append(argv[2:])
    return commands


COMMANDS = readme_commands()


def test_the_readme_has_its_commands() -> None:
    modules = {argv[0] for argv in COMMANDS}
    assert {"mfg_lightning.train", "mfg_lightning.evaluate", "mfg_lightning.data.check",
            "mfg_lightning.data.export", "mfg_lightning.reproduce"} <= modules  # fmt: skip
    assert len(COMMANDS) >= 30


def _first_values(overrides: list[str]) -> list[str]:
    """A multirun's ``key=a,b,c`` as its first job's ``key=a`` (brackets and quotes kept)."""
    out = []
    for o in overrides:
        key, sep, value = o.partition("=")
        if sep and "," in value and not value.startswith(("[", "{", "'", '"')):
            value = value.split(",")[0]
        out.append(f"{key}{sep}{value}")
    return out


@pytest.mark.parametrize(
    "argv",
    [a for a in COMMANDS if a[0] in CONFIGS],
    ids=lambda a: " ".join(a)[:90],
)
def test_readme_command_composes(argv: list[str]) -> None:
    overrides = [a for a in argv[1:] if a not in ("-m", "--multirun")]
    cfg = compose(CONFIGS[argv[0]], _first_values(overrides))
    assert cfg is not None and len(cfg) > 0
