"""Reading Markdown for the documentation tests (test_readme): its sentences and their words, the
lines wider than the wrap, and the timings with no date and machine beside them.

What is read:

- **Prose**: paragraphs and list items outside fenced code blocks, HTML lines (``<img>``,
  comments) and headings. Inline code counts as one word and links as their text. A sentence
  ends at ``.``, ``!`` or ``?`` before a capital, a digit or an opening mark.
- **Tables**: each cell is held to the sentence rule like prose (a cell that needs more than 40
  words belongs in a paragraph). Table rows may be wider than the wrap.
- **Generated blocks**: the lines between ``<!-- name:start -->`` and ``<!-- name:end -->`` for
  a name in :data:`GENERATED` are written by a program from a template, and are left to it.
- **Timings**: a number followed by a unit of time (``ms``, ``s``, ``min``, ``minutes``, ``h``,
  ``hours``, ``days``), outside code. It counts as dated when its sentence (in a table: its row or
  the table's header row) names a date, YYYY-MM-DD, and a machine kind (:data:`MACHINE`). A
  duration that is a setting, not a measurement, is written as code: ```timeout_min: 120```.
"""

from __future__ import annotations

import re

#: No sentence longer than this (BRIEF: one idea a sentence, under 40 words).
MAX_WORDS = 40
#: The wrap of every line outside code blocks and tables.
MAX_COLUMNS = 100
#: Blocks between ``<!-- name:start/end -->`` written by a program: the study's verdict table
#: (``mfg_lightning.study.report``, from ``study/templates/report/readme.md.j2``).
GENERATED = ("reproduction-table",)

DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
#: A CPU or GPU kind, as the bench results name them.
MACHINE = re.compile(r"EPYC|Xeon|AVX2|AVX-?512|AMX|H100|H200|A100|V100", re.I)
TIMING = re.compile(
    r"(?<![\w.,/-])\d[\d,]*(?:\.\d+)?(?:\s?[–-]\s?\d[\d,]*(?:\.\d+)?)?"
    r"\s?(?:ms|s|sec|seconds?|mins?|minutes?|h|hrs?|hours?|days?)(?![\w-])"
)
# inline code is kept, between these marks, so that a date or machine named in code counts
_CODE_START, _CODE_END = "\x02", "\x03"
_SENTENCE_END = re.compile(r"(?<=[.!?])[\"')\]*_]*\s+(?=[A-Z0-9(\"'\[*_\x02])")
_ITEM = re.compile(r"^\s*(?:[-*+]|\d+\.)\s+")


def _clean(text: str) -> str:
    """Markdown to plain words: inline code marked, links and images as their text, HTML tags
    and emphasis marks dropped."""
    text = re.sub(r"`+([^`]*)`+", lambda m: _CODE_START + m.group(1) + _CODE_END, text)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"<[^>]+>", "", text)
    return re.sub(r"\*\*|__", "", text)


def _without_code(text: str) -> str:
    return re.sub(f"{_CODE_START}[^{_CODE_END}]*{_CODE_END}", " ", text)


def _lines(text: str) -> list[tuple[int, str, str]]:
    """``(number, line, kind)`` of every line outside code blocks and generated blocks, kind
    ``prose``, ``table``, ``break`` (blank, heading or HTML: it ends a paragraph)."""
    out, in_code, generated = [], False, None
    for n, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        marker = re.fullmatch(r"<!--\s*([\w-]+):(start|end)\s*-->", stripped)
        if marker and marker.group(1) in GENERATED:
            generated = marker.group(1) if marker.group(2) == "start" else None
            continue
        if stripped.startswith("```"):
            in_code = not in_code
            continue
        if in_code or generated:
            continue
        if stripped.startswith("|"):
            out.append((n, line, "table"))
        elif not stripped or stripped.startswith(("#", "<")):
            out.append((n, line, "break"))
        else:
            out.append((n, line, "prose"))
    return out


def _split(line: int, text: str, offsets: list[tuple[int, int]]) -> list[tuple[int, str]]:
    """The sentences of ``text``, each with the line it starts on (``offsets``: where in
    ``text`` each source line starts)."""
    out, at = [], 0
    for part in _SENTENCE_END.split(text):
        start = text.find(part, at)
        at = start + len(part)
        n = max((ln for ln, off in offsets if off <= start), default=line)
        if part.strip():
            out.append((n, part.strip()))
    return out


def _units(text: str) -> list[tuple[str, int, str, str]]:
    """``(kind, line, text, scope)``: each prose sentence (its scope itself) and each table cell
    (its scope the row and the table's header row)."""
    units: list[tuple[str, int, str, str]] = []
    para: list[tuple[int, str]] = []
    header = ""

    def flush() -> None:
        if para:
            joined, offsets = "", []
            for n, line in para:
                offsets.append((n, len(joined)))
                joined += _clean(line.strip()) + " "
            units.extend(("prose", n, s, s) for n, s in _split(para[0][0], joined, offsets))
            para.clear()

    previous = "break"
    for n, line, kind in _lines(text):
        if kind == "table":
            flush()
            cells = [_clean(c.strip()) for c in line.strip().strip("|").split("|")]
            if all(re.fullmatch(r":?-+:?", c) for c in cells if c):
                continue
            if previous != "table":
                header = " ".join(cells)
            for cell in cells:
                units.extend(("cell", n, s, " ".join(cells) + " " + header)
                             for _, s in _split(n, cell, [(n, 0)]))  # fmt: skip
        elif kind == "prose":
            if _ITEM.match(line):
                flush()
            para.append((n, line))
        else:
            flush()
        previous = kind
    flush()
    return units


def sentences(text: str) -> list[tuple[int, str]]:
    """``(line, sentence)`` of the prose and the table cells of a Markdown text."""
    return [(n, s.replace(_CODE_START, "`").replace(_CODE_END, "`")) for _, n, s, _ in _units(text)]


def words(sentence: str) -> int:
    """The words of a sentence: inline code counts as one."""
    sentence = re.sub(r"`[^`]*`", "code", sentence)
    return sum(1 for w in sentence.split() if re.search(r"\w", w))


def wide_lines(text: str) -> list[tuple[int, int]]:
    """``(line, width)`` of the lines wider than :data:`MAX_COLUMNS` outside code blocks and
    tables, a link's target not counted (a URL cannot be wrapped)."""
    out = []
    for n, line, kind in _lines(text):
        if kind == "table":
            continue
        width = len(re.sub(r"\]\([^)]*\)", "]()", re.sub(r'(src|href)="[^"]*"', "", line)))
        if width > MAX_COLUMNS:
            out.append((n, width))
    return out


def undated_timings(text: str) -> list[tuple[int, str]]:
    """``(line, timing)`` of each timing whose sentence or table row names no date or no
    machine kind."""
    out = []
    for _, n, unit, scope in _units(text):
        for m in TIMING.finditer(_without_code(unit)):
            if not (DATE.search(scope) and MACHINE.search(scope)):
                out.append((n, m.group(0)))
    return out


def yaml_comments(text: str) -> str:
    """The comments of a YAML file as text, line for line (other lines left empty), so that
    :func:`undated_timings` reads them as prose with the file's line numbers."""
    out = []
    for line in text.splitlines():
        # a '#' that starts a comment: at the line's start or after a space, outside quotes
        comment = ""
        quote = None
        for i, ch in enumerate(line):
            if quote:
                quote = None if ch == quote else quote
            elif ch in "'\"":
                quote = ch
            elif ch == "#" and (i == 0 or line[i - 1].isspace()):
                comment = line[i:].lstrip("#").strip()
                break
        out.append(comment)
    return "\n".join(out)
