"""The paper's sentences that the reproduction study judges: where each is, its words, and how
it is measured here (:class:`Sentence`, :data:`SENTENCES`). The words live in
``templates/sentences.yaml``, where a scientist edits them; the verdict code that reads them is
:mod:`mfg_lightning.study.sentences`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mfg_lightning.core.config import load_yaml_mapping
from mfg_lightning.study.render import TEMPLATES

__all__ = ["SENTENCES", "Sentence", "load_sentences"]


@dataclass(frozen=True)
class Sentence:
    """One sentence of the paper: where it is, its words, and how it is measured here."""

    key: str
    where: str
    quote: str
    measured: str
    short: str = ""
    #: the input flow its measurements use; ``{study}`` is the study's own flow (DIS)
    flow: str = "{study}"


def load_sentences(path: Path = TEMPLATES / "sentences.yaml") -> dict[str, Sentence]:
    """A sentences file (``templates/sentences.yaml``) as sentences by key (S1, S2, …), in the
    file's order. A key given twice, a missing or unknown field is refused with the file and the
    sentence named."""
    required, optional = {"where", "quote", "measured", "short"}, {"flow"}
    out = {}
    for key, row in load_yaml_mapping(path).items():
        if not isinstance(row, dict):
            raise ValueError(f"{path}: sentence {key}: expected its fields, got {row!r}")
        # a misspelt field would silently fall back to a default: name it instead
        unknown, missing = set(row) - required - optional, required - set(row)
        if unknown or missing:
            raise ValueError(f"{path}: sentence {key}: unknown field(s) {sorted(unknown)}, "
                             f"missing field(s) {sorted(missing)}")  # fmt: skip
        out[str(key)] = Sentence(str(key), **{k: str(v) for k, v in row.items()})
    return out


#: The judged sentences, by key.
SENTENCES: dict[str, Sentence] = load_sentences()
