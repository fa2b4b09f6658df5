"""The README and the docs keep their words: each Hydra command composes as written, the README
stays a short map with the main job on its first screen, and every relative link resolves.

Commands are read from the ``bash`` blocks of README.md and docs/*.md. A multirun's
comma-separated sweep takes its first value (composing is per job); placeholders such as
``<date>`` or ``...`` stand for values, and composing checks keys, groups and options, not files.
The ones that need no data also run, as tiny trainings, in test_train, test_rendered_flow,
test_loggers and test_sweeps.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from conftest import REPO
from mfg_lightning.core.config import compose

#: The documents whose commands and links are checked: the README, the pages it links to and
#: the contributor's guide.
DOCUMENTS = [
    REPO / "README.md",
    REPO / "CONTRIBUTING.md",
    REPO / "CHANGELOG.md",
    *sorted((REPO / "docs").glob("*.md")),
]
#: The README's budget: a map, not a manual (the depth is in docs/).
README_MAX_LINES = 250
#: The main job (training on KITTI or Virtual KITTI) is on the first screen.
MAIN_JOB_WITHIN = 60

#: ``python -m <module>`` → its config (the Hydra entry points).
CONFIGS = {
    "mfg_lightning.train": "train",
    "mfg_lightning.train_flow": "train_flow",
    "mfg_lightning.evaluate": "evaluate",
    "mfg_lightning.predict": "predict",
    "mfg_lightning.analyze_basis": "analyze_basis",
    "mfg_lightning.reproduce": "reproduce",
    "mfg_lightning.data.check": "check",
    "mfg_lightning.data.export": "export",
}


def document_commands(path: Path) -> list[list[str]]:
    """The ``python -m mfg_lightning…`` commands of a Markdown file, as argv lists
    (``mfg-eval-poses``, an argparse command, is tested in test_evaluate_poses)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", path.read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            # a placeholder (<date>, <run dir>) stands for a value the user fills in
            argv = shlex.split(re.sub(r"<[^<>]+>", "PLACEHOLDER", line), comments=True)
            if argv[:2] == ["python", "-m"] and argv[2].startswith("mfg_lightning"):
                commands.append(argv[2:])
    return commands


README_COMMANDS = document_commands(REPO / "README.md")
COMMANDS = [argv for path in DOCUMENTS for argv in document_commands(path)]


def test_the_readme_has_its_commands() -> None:
    modules = {argv[0] for argv in README_COMMANDS}
    assert {"mfg_lightning.train", "mfg_lightning.evaluate", "mfg_lightning.data.check",
            "mfg_lightning.predict", "mfg_lightning.reproduce"} <= modules  # fmt: skip
    # the docs hold the rest: the export, and many more of each
    assert "mfg_lightning.data.export" in {argv[0] for argv in COMMANDS}
    assert len(COMMANDS) >= 50


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
    # the same command in two documents is composed once
    [list(a) for a in dict.fromkeys(tuple(a) for a in COMMANDS if a[0] in CONFIGS)],
    ids=lambda a: " ".join(a)[:90],
)
def test_documented_command_composes(argv: list[str]) -> None:
    overrides = [a for a in argv[1:] if a not in ("-m", "--multirun")]
    cfg = compose(CONFIGS[argv[0]], _first_values(overrides))
    assert cfg is not None and len(cfg) > 0


def test_the_sbatch_example_ends_every_task_when_one_fails() -> None:
    """docs/scaling.md's job script starts its tasks with ``srun --kill-on-bad-exit=1``: an NCCL
    task does not notice a dead peer and would wait in its next collective for 30 minutes."""
    lines = (REPO / "docs" / "scaling.md").read_text().splitlines()
    sruns = [line for line in lines if line.startswith("srun ")]
    assert sruns and all(line.split()[1] == "--kill-on-bad-exit=1" for line in sruns), sruns


def test_the_readme_is_a_short_map_with_the_main_job_first() -> None:
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines"
    main_job = re.compile(r"^python -m mfg_lightning\.train\b.*\bdataset=v?kitti\b")
    first = next((n for n, line in enumerate(lines, 1) if main_job.match(line)), None)
    assert first is not None, "README.md shows no training on KITTI or Virtual KITTI"
    assert first <= MAIN_JOB_WITHIN, f"the main job first appears at line {first}"


def _anchors(path: Path) -> set[str]:
    """The heading anchors of a Markdown file as GitHub forms them (lower case, punctuation
    dropped, spaces to hyphens)."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    headings = re.findall(r"^#{1,6}\s+(.+?)\s*$", text, re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings}


def _links(path: Path) -> list[str]:
    """The targets of a Markdown file's links and images (``[..](target)``, ``src="target"``),
    outside code blocks and inline code."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"\]\(([^)\s]+)\)", text) + re.findall(r'src="([^"]+)"', text)


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(path: Path) -> None:
    broken = []
    for link in _links(path):
        if re.match(r"[a-z][a-z0-9+.-]*:", link):  # https:, mailto:: not this repository's
            continue
        target, _, anchor = link.partition("#")
        file = (path.parent / target).resolve() if target else path
        if not file.exists():
            broken.append(f"{link}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            broken.append(f"{link}: no heading with that anchor")
    assert not broken, f"{path.relative_to(REPO)}: " + "; ".join(broken)
