"""The paper's sentences that the reproduction study judges: where each is, its words, and how
it is measured here (:class:`Sentence`, :data:`SENTENCES`). The words live in
``templates/sentences.yaml``, where a scientist edits them; the verdict code that reads them is
:mod:`mfg_lightning.study.sentences`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

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
    file's order."""
    rows = yaml.safe_load(path.read_text(encoding="utf-8"))
    fields = {"where", "quote", "measured", "short", "flow"}
    for key, row in rows.items():
        # a misspelt field would silently fall back to a default: name it instead
        unknown = set(row) - fields
        if unknown:
            raise ValueError(f"{path}: sentence {key}: unknown field(s) {sorted(unknown)}")
    return {str(k): Sentence(str(k), **r) for k, r in rows.items()}


#: The judged sentences, by key.
SENTENCES: dict[str, Sentence] = load_sentences()
