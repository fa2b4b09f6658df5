"""The README's headline and the words beside the learned flow and S10 follow the findings: the
headline row names the one part that decides each verdict; the learned-flow words move when its
RPE translation moves against the DIS seeds' range; S10 prints the strict rule's verdict and the
rule stated before's, and says when bins below the floor leave it unable to hold."""

from __future__ import annotations

import numpy as np
import pytest

from mfg_lightning.study import findings as F
from mfg_lightning.study.intervals import Interval
from mfg_lightning.study.objects import object_sentences
from mfg_lightning.study.parts import Judged, Part, Settled
from mfg_lightning.study.quotes import SENTENCES
from mfg_lightning.study.render import paragraph
from mfg_lightning.study.report import readmetable


def _part(label: str, lo: float, hi: float, bound: float = 1.0) -> Part:
    mid = (lo + hi) / 2
    return Part(label, Interval(mid, lo, hi, "t", ((4, (hi - lo) / 2 / 2.776),)), bound, "<=")


def _readme(*parts: Part, models: dict | None = None) -> list[str]:
    return readmetable([Judged(SENTENCES["S1"], list(parts)).close()], "r.md", models or {}, 7200)


def _row(*parts: Part) -> str:
    return next(r for r in _readme(*parts) if r.startswith("| S1 "))


def test_the_headline_names_the_part_that_decides() -> None:
    # holds: the binding part, the one nearest its bound, with one number, one interval and
    # the bound in its own column
    row = _row(_part("far", 0.1, 0.2), _part("near", 0.8, 0.95), _part("mid", 0.5, 0.7))
    assert "| near: 0.875 [0.800, 0.950] | ≤ 1.000 | holds |" in row
    # does not hold: the failing part, whatever else holds
    row = _row(_part("far", 0.1, 0.2), _part("fails", 1.5, 1.9))
    assert "| fails: 1.700 [1.500, 1.900] | ≤ 1.000 | does not hold |" in row
    # inconclusive: the part Holm's procedure stopped at (the most decisive undecided one), its
    # 95 % interval only (the level Holm's procedure judged it at is the report's)
    row = _row(_part("wide", 0.0, 3.0), _part("close", 0.95, 1.25))
    assert "| close: 1.100 [0.950, 1.250] | ≤ 1.000 | inconclusive |" in row
    assert "Holm" not in row and row.count("[") == 1
    assert row.count("|") == 6  # one line, one part
    row = _row(_part("far", 0.1, 0.2), _part("near", 0.2, 0.3), _part("wide", 0.0, 3.0))
    assert row.endswith("| partly |")


def test_the_readme_counts_the_verdicts_and_the_cost() -> None:
    models = {"a": {"cpu_kind": "avx2", "precision": "32-true"}, "b": {"cpu_kind": "avx2"},
              "c": {}}  # fmt: skip
    text = _readme(_part("far", 0.1, 0.2), models=models)
    assert text[0] == "1 holds; 3 models, 2 hours on avx2 CPUs (2), not recorded (1)."
    assert all(len(line) <= 100 for line in text if not line.startswith("|"))
    prose = " ".join(line for line in text if line and not line.startswith("|"))
    assert all(len(s.split()) < 40 for s in prose.split(". "))


def _learned(rpe_trans: float) -> str:
    f = F.LearnedFlow(
        {"ATE † 09": (0.0165, 0.0159, 0.0173, 4), "ATE * 09": (0.0339, 0.0413, 0.0485, 4),
         "RPE translation": (rpe_trans, 0.0633, 0.0762, 4),
         "RPE rotation": (0.00150, 0.00141, 0.00168, 5)},
        {"all": (2.45, 5.43), "road": (2.89, 9.11), "far": (1.28, 1.27)},
    )  # fmt: skip
    learned = {"steps": 9000, "convergence": {"converged": True}}
    return paragraph("report/learned.md.j2", learned=learned, flow="DIS", table="", f=f, n=3,
                     seed=None)  # fmt: skip


@pytest.mark.parametrize(
    ("rpe_trans", "words"),
    [
        (0.0802, "did not bring a better RPE translation (it is worse than the seeds' range)"),
        (0.0700, "did not bring a better RPE translation (it is within the seeds' range)"),
        (0.0500, "the lower error on the near pixels goes with a better RPE translation;"),
    ],
)
def test_the_learned_flow_words_follow_its_rpe_translation(rpe_trans: float, words: str) -> None:
    text = _learned(rpe_trans)
    assert words in text
    assert "several times lower than it on the road (2.89 against 9.11 px)" in text
    assert "the error on the far pixels is about the same, and the RPE rotation is within" in text
    assert "better than the range for ATE * 09; and within the range for ATE † 09." in text


def _seed(seed: int, pairs: tuple[int, int, int, int], n: int = 20) -> dict:
    """An exact-flow seed's objects in 2 sizes × 2 speeds: bin 0 where nothing is detected (the
    filters, the threshold and no motion err alike), the others where the filters halve the
    error; each bin's objects in ``pairs`` test pairs."""
    rng = np.random.default_rng(seed)
    pix = np.zeros((n, 4))
    for b, k in enumerate(pairs):
        pix[:k, b] = 10.0
    speed = pix * 20.0
    speed[:, 0] = pix[:, 0]
    f_err, t_err = speed * rng.uniform(0.45, 0.5, (n, 1)), speed * 0.9
    f_err[:, 0] = t_err[:, 0] = speed[:, 0]
    counts = {"tp": rng.integers(5, 10, n).tolist(), "fp": [1] * n, "fn": [1] * n}
    side = {k: {**counts, "pixels": pix.tolist(), "err": e.tolist()}
            for k, e in (("filters", f_err), ("threshold", t_err))}  # fmt: skip
    return {"objects": {"size_bins": [0, 0.005, 1], "speed_bins": [0, 2, 999],
                        "pairs": {**side, "speed": speed.tolist()}}}  # fmt: skip


@pytest.mark.parametrize(
    ("pairs", "before", "floor_words"),
    [
        ((20, 20, 3, 0), "“partly”", "2 of the 4 size × speed bins hold objects in fewer than 10"),
        ((20, 20, 20, 20), "“holds”", "Each of the 4 size × speed bins holds objects in at least"),
    ],
)
def test_s10_prints_both_readings_and_its_unmeasured_bins(
    pairs: tuple[int, int, int, int], before: str, floor_words: str
) -> None:
    settled = Settled(seeds={"exact": {s: _seed(s, pairs) for s in range(3)}})
    j10 = object_sentences(settled)[1].close()
    assert j10.verdict == "does not hold"  # the strict rule: bin 0 lies on its bound
    assert "Under the strict rule S10's verdict is “does not hold”" in j10.beside
    assert f"under the rule stated before it would be {before}" in j10.beside
    assert "0.000 [0.000, 0.000]" in j10.beside and floor_words in j10.beside
    assert ("cannot hold" in j10.beside) == (min(pairs) < 10)
