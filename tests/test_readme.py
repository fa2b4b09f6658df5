"""The README and the docs keep their words: each Hydra command composes as written, the README
stays a short map with what a newcomer needs on its first screen, every relative link resolves,
sentences stay short, lines stay within 100 columns, and every timing names its date and machine.

Commands are read from the ``bash`` blocks of README.md and docs/*.md, and from inline code in
their tables. A multirun's comma-separated sweep takes its first value (composing is per job);
placeholders such as ``<date>`` or ``...`` stand for values, and composing checks keys, groups and
options, not files. The ones that need no data also run, as tiny trainings, in test_train,
test_rendered_flow, test_loggers and test_sweeps.

The prose rules (:mod:`prose`) hold for the whole README and for the first screen
(:data:`FIRST_SCREEN` lines) of every page in docs/; the timing rule holds for every document and
every config comment.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

import prose
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
#: A screen: the README's first holds the description, a figure, install, the quick start with
#: its result and the task table; a docs page's first is held to the prose rules.
FIRST_SCREEN = 60

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
    """The ``python -m mfg_lightning…`` commands of a Markdown file, as argv lists: every line of
    its ``bash`` blocks and the inline code of its tables' cells (``mfg-eval-poses``, an argparse
    command, is tested in test_evaluate_poses)."""
    text = path.read_text()
    lines = [
        line
        for block in re.findall(r"```bash\n(.*?)```", text, re.S)
        for line in block.replace("\\\n", " ").splitlines()
    ]
    lines += [
        code
        for row in re.findall(r"^\|.*\|$", text, re.M)
        for code in re.findall(r"`(python -m mfg_lightning[^`]*)`", row)
    ]
    commands = []
    for line in lines:
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


def test_the_readme_is_a_short_map_with_what_a_newcomer_needs_first() -> None:
    """Within the first screen: one sentence on what the project is, a figure, the install, the
    quick start with its time, machine and expected result, and the table of tasks."""
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines"
    screen = "\n".join(lines[:FIRST_SCREEN])
    description = screen.split("\n\n")[1]
    assert not description.startswith(("<", "#", "!")) and description.count(". ") == 0
    assert re.search(r'<img src="docs/img/[^"]+\.png"|!\[[^]]*\]\(docs/img/', screen)
    install = screen.split("## Install")[1].split("\n## ")[0]
    assert "venv" in install and "make install" in install and "pip install -e ." in install
    quick = screen.split("## Quick start")[1].split("\n## ")[0]
    assert "python -m mfg_lightning.train " in quick
    assert re.search(r"\b\d+ s on .*(EPYC|Xeon).*20\d\d-\d\d-\d\d", quick), "the time, its machine"
    assert re.search(r"ATE near 0\.0\d+ m", quick) and "RPE rotation near" in quick
    assert "outputs/train/runs/" in quick, "what the quick start writes"
    tasks = screen.split("## Tasks")[1].split("\n## ")[0]
    rows = [r for r in tasks.splitlines() if r.startswith("| ") and "---" not in r][1:]
    commands = " ".join(rows)
    for needed in (
        "dataset=kitti",
        "dataset=vkitti",
        "hparams_search=sparsity",
        "tensorboard --logdir",
        "mfg-eval-poses",
        "mfg_lightning.reproduce",
    ):
        assert needed in commands, f"the task table has no {needed}"
    assert all(len(row.split(" | ")) == 3 for row in rows), "task | command | typical time"


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


#: The pages held to the prose rules: the README whole, each docs page's first screen.
PROSE_PAGES = [(REPO / "README.md", None)] + [
    (path, FIRST_SCREEN) for path in sorted((REPO / "docs").glob("*.md"))
]


@pytest.mark.parametrize(
    "path, lines", PROSE_PAGES, ids=[str(p.relative_to(REPO)) for p, _ in PROSE_PAGES]
)
def test_sentences_are_short_and_lines_wrapped(path: Path, lines: int | None) -> None:
    text = "\n".join(path.read_text().splitlines()[:lines])
    long = [
        f"line {n}: {len(s.split())} words: {s[:80]}…"
        for n, s in prose.sentences(text)
        if prose.words(s) > prose.MAX_WORDS
    ]
    wide = [f"line {n}: {width} columns" for n, width in prose.wide_lines(text)]
    assert not long and not wide, "; ".join(long + wide)


TIMED = [REPO / "README.md", REPO / "CONTRIBUTING.md", *sorted((REPO / "docs").glob("*.md"))]


@pytest.mark.parametrize("path", TIMED, ids=lambda p: str(p.relative_to(REPO)))
def test_every_timing_in_the_docs_names_its_date_and_machine(path: Path) -> None:
    bare = prose.undated_timings(path.read_text())
    assert not bare, f"{path.relative_to(REPO)}: " + "; ".join(f"line {n}: {s}" for n, s in bare)


def test_every_timing_in_the_configs_names_its_date_and_machine() -> None:
    bare = [
        f"{path.relative_to(REPO)}:{n}: {s}"
        for path in sorted((REPO / "conf").rglob("*.yaml"))
        for n, s in prose.undated_timings(prose.yaml_comments(path.read_text()))
    ]
    assert not bare, "; ".join(bare)


def test_the_prose_rules_read_what_they_should() -> None:
    """The rules' own reading, on a page made for it: code, tables, links and generated blocks."""
    page = "\n".join([
        "# Title",
        "",
        "One short sentence. " + "word " * 41 + "ends here.",
        "",
        "```bash",
        "python -m x " + "y " * 60,
        "```",
        "",
        "| a | " + "cell " * 45 + "|",
        "",
        "It took 12 s on 2 AMD EPYC cores (2026-12-07). It took 3 min there.",
        "A `timeout: 30 s` is a setting, and [a link](" + "x" * 100 + ") may run long.",
        "",
        "| run | time |",
        "| --- | ---: |",
        "| Xeon, 2026-12-05 | 5 s |",
        "| somewhere | 7 s |",
    ])  # fmt: skip
    long = [n for n, s in prose.sentences(page) if prose.words(s) > prose.MAX_WORDS]
    assert long == [3, 9]  # the 44-word sentence and the 45-word table cell; never code
    # line 3 is wider than the wrap; code, tables and a link's target may run long
    assert [n for n, _ in prose.wide_lines(page)] == [3]
    assert [(n, s) for n, s in prose.undated_timings(page)] == [(11, "3 min"), (17, "7 s")]
    assert prose.yaml_comments("a: 1  # took 5 s\n# and 6 min\nb: '7 s'\n") == (
        "took 5 s\nand 6 min\n"
    )
