"""The report's words are templates rendered from typed findings: a finding moved across a bound
(a ratio from ×1.2 to ×5, an interval from one side of its bound to the other, a verdict from
holds to does not hold) changes the rendered words with it; no template types a conclusion word;
the stage table of ``conf/reproduce.yaml`` is the one list the study runs and the report reads."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from mfg_lightning.study import findings as F
from mfg_lightning.study.noise import Spread
from mfg_lightning.study.quotes import SENTENCES, load_sentences
from mfg_lightning.study.render import TEMPLATES, lines, paragraph, unwrap


def _reading(name: str, **findings: object) -> str:
    return paragraph(f"reading/{name}.md.j2", **findings)


def _central(far: float) -> str:
    f = F.Central(
        {"09": 1.8, "10": 1.7},
        {"09": 1.67, "10": 1.77},
        {"09": (1.5, 2.0), "10": (1.5, 2.0)},
        [(1, 1.0, 5.0), (2, far, 9.0)],
        far,
    )
    return _reading("central", f=f)


@pytest.mark.parametrize(
    ("far", "words", "not_words"),
    [
        (1.2, "flows worse than the † one", "several times"),
        (2.0, "flows much worse than the † one", "several times"),
        (5.0, "flows several times worse than the † one", "much worse"),
    ],
)
def test_the_offset_ratio_words_follow_the_ratio(far: float, words: str, not_words: str) -> None:
    text = _central(far)
    assert words in text and not_words not in text
    assert f"×{far:.1f} that at ±1" in text


def test_the_classical_range_decides_what_the_ratio_measures() -> None:
    inside = _central(1.2)
    assert "inside that range on 09 and 10: the ratio measures the flow" in inside
    f = F.Central(
        {"09": 3.0, "10": 1.7}, {"09": 1.67, "10": 1.77}, {"09": (1.5, 2.0), "10": (1.5, 2.0)}
    )
    above = _reading("central", f=f)
    assert "above that range on 09, inside that range on 10" in above and "mixes" in above
    assert "has not been measured yet" in above


def _table2(g: F.FlowGain, c: F.Table2Contrast | None = None) -> str:
    runs = [{"flow": "exact", "steps": 6000, "mfg": g.mfg_exact, "irls": g.irls_exact}]
    return _reading(
        "table2", runs=runs, pairs=1696, printed=("0.0011", "0.0014"), g=g, c=c, main_pairs=25838
    )


def test_the_exact_flow_gain_words_follow_the_two_falls() -> None:
    """IRLS gaining ×1.2 more than MFG: "more", and no explanation; ×5: "several times more"
    with the explanation a large gain needs."""
    small = _table2(F.FlowGain(0.001, 0.0012, 0.001, 0.0012 * 1.2))
    assert "helping IRLS more than MFG. The paper's" in small and "regressor" not in small
    large = _table2(F.FlowGain(0.001, 0.0012, 0.001, 0.0012 * 5))
    assert "helping IRLS several times more than MFG: on flow without" in large
    assert "falls ×6.0" in large and "MFG's rises" not in large


def test_the_full_split_contrast_needs_the_seeds_interval_below_the_best() -> None:
    g = F.FlowGain(0.001, 0.0012, 0.001, 0.002)
    beats = F.Table2Contrast(Spread((0.0006, 0.00062, 0.00061)), 0.0012, 0.001, 5.0)
    text = _table2(g, beats)
    assert "beats every classical method" in text
    assert "is several times worse than the robust continuous one" in text
    assert "is worse than the robust continuous one" in _table2(
        g, F.Table2Contrast(beats.full, 0.0012, 0.001, 1.2)
    )
    # the seeds' interval reaches the best classical method: no contrast is claimed
    wide = F.Table2Contrast(Spread((0.0004, 0.0009, 0.0006)), 0.0012, 0.0007, 5.0)
    assert "beats" not in _table2(g, wide) and not wide.contrast


def test_the_size_curve_words_follow_irls_over_mfgs_lowest() -> None:
    def curve(irls: float) -> str:
        return _reading(
            "size", f=F.SizeCurve([(800, Spread((0.0014,))), (6400, Spread((0.001,)))], irls)
        )

    assert "an error larger than MFG's lowest" in curve(0.0012)
    assert "an error several times larger than MFG's lowest" in curve(0.005)
    assert "above IRLS's at every size measured" in curve(0.0009)
    assert "below IRLS's at 6\u202f400 pairs" in curve(0.0012)


def test_the_essential_matrix_reading_follows_their_growths() -> None:
    def robust(g: float) -> str:
        f = F.Robustness([0.0, 0.1, 1.0], [10, 5], 1.2, 0.9, {"RANSAC": g}, [g])
        return _reading("robustness", f=f)

    falls = "rotation errors are lower where moving objects cover more"
    assert falls in robust(0.2)
    assert falls not in robust(1.2) and robust(1.2).endswith("RANSAC ×1.20.")


def test_the_input_scale_words_follow_where_it_falls_against_the_band() -> None:
    val = Spread((0.0200, 0.0202, 0.0198))

    def scale(ate: float) -> str:
        return _reading("input_scale", f=F.InputScale(0.2, 1.0, val, ate))

    assert "lower, beyond the tolerance" in scale(0.019) and "making 0.2 the default" in scale(
        0.019
    )
    assert "within the tolerance" in scale(0.0199) and "contradicts" in scale(0.021)
    assert "not measured yet" in _reading(
        "input_scale", f=F.InputScale(0.2, 1.0, Spread((0.02,)), 0.019)
    )


def test_the_verdict_count_follows_a_verdict_from_holds_to_does_not_hold() -> None:
    def judged(verdict: str) -> list:
        return [
            SimpleNamespace(verdict=verdict, sentence=SimpleNamespace(key="S1")),
            SimpleNamespace(verdict="partly (1 of 2)", sentence=SimpleNamespace(key="S2")),
        ]

    holds = _reading("verdicts", by=F.verdict_count(judged("holds")))
    fails = _reading("verdicts", by=F.verdict_count(judged("does not hold")))
    assert holds == "**The verdicts.** holds: S1; partly: S2."
    assert fails == "**The verdicts.** does not hold: S1; partly: S2."


def test_unwrap_joins_a_paragraph_and_keeps_tables_lists_and_headings() -> None:
    text = "## Head\n\nOne\ntwo.\n\n| a |\n|---|\n\n- item\n  goes on\n- next\n"
    assert unwrap(text) == [
        "## Head",
        "",
        "One two.",
        "",
        "| a |",
        "|---|",
        "",
        "- item   goes on",
        "- next",
        "",
    ]


def test_no_template_types_a_conclusion_word() -> None:
    """ "Several times" and "much" come from the wording filters, never from a template."""
    fixed = re.compile(r"several times|\bmuch (better|worse|larger|smaller|more|less)\b")
    for path in TEMPLATES.rglob("*.j2"):
        assert not fixed.search(path.read_text()), path.name


def test_a_missing_finding_is_an_error_not_an_empty_word() -> None:
    from jinja2 import UndefinedError

    with pytest.raises(UndefinedError):
        lines("reading/central.md.j2")


def test_the_sentences_file_names_a_misspelt_missing_or_repeated_field(tmp_path: Path) -> None:
    bad = tmp_path / "sentences.yaml"
    entry = "  where: Abstract\n  quote: q\n  measured: m\n"
    bad.write_text(f"S1:\n{entry}  shrot: s\n", "utf-8")
    with pytest.raises(ValueError, match=r"sentences.yaml: sentence S1: unknown.*shrot.*short"):
        load_sentences(bad)
    bad.write_text(f"S1:\n{entry}  short: s\nS1:\n{entry}  short: t\n", "utf-8")
    with pytest.raises(yaml.YAMLError, match="key 'S1' given twice") as twice:
        load_sentences(bad)
    assert f'"{bad}", line 6' in str(twice.value)  # the file and the second key's line
    bad.write_text("S1:\n", "utf-8")
    with pytest.raises(ValueError, match="sentence S1: expected its fields"):
        load_sentences(bad)
    assert load_sentences() == SENTENCES and list(SENTENCES) == [f"S{i}" for i in range(1, 11)]
