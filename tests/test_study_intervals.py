"""The verdicts' intervals (:mod:`mfg_lightning.study.intervals`) by hand, and every sentence's
verdict code on hand-made results: values on the claimed side of each bound hold, values on the
wrong side never do (they do not hold, or are inconclusive)."""

from __future__ import annotations

import gc
import json
import math
import statistics
from pathlib import Path

import numpy as np
import pytest
from arch.bootstrap import MovingBlockBootstrap
from scipy import stats
from statsmodels.stats.multitest import multipletests

from mfg_lightning.core.config import compose
from mfg_lightning.study.intervals import (
    HOLDS,
    INCONCLUSIVE,
    NO_VERDICT,
    NOT_HOLD,
    PARTLY,
    Claim,
    Interval,
    bootstrap_se,
    combine,
    difference,
    holm,
    interval,
    interval_verdict,
    median_interval,
    quantile,
    t_quantile,
)
from mfg_lightning.study.sentences import Settled, judge_all, seed_views

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results" / "reproduction"

# -- the construction ---------------------------------------------------------------------------


def test_t_quantiles_match_the_tables() -> None:
    for df, t in ((1, 12.706), (2, 4.303), (4, 2.776), (10, 2.228), (30, 2.042)):
        assert t_quantile(df) == pytest.approx(t, abs=1e-3)
    with pytest.raises(ValueError, match="degree"):
        t_quantile(0)


def test_quantiles_at_the_levels_holm_reads() -> None:
    # t(2) at 99.9 %, t(4) at 99 %, t(1) at 99.99 % (the Cauchy: tan(π/2 · 0.9999)), the normal
    assert t_quantile(2, 0.999) == pytest.approx(31.599, abs=1e-3)
    assert t_quantile(4, 0.99) == pytest.approx(4.604, abs=1e-3)
    assert t_quantile(1, 0.9999) == pytest.approx(math.tan(math.pi / 2 * 0.9999), rel=1e-6)
    assert quantile(0) == pytest.approx(1.95996, abs=1e-5) and quantile(3) == t_quantile(3)
    with pytest.raises(ValueError, match="level"):
        t_quantile(3, 1.0)


def test_an_interval_rebuilt_at_another_level() -> None:
    xs = [1.0, 1.2, 1.1]
    iv = interval(xs, [0.03, 0.04])
    assert iv.at(0.95) is iv
    wide = iv.at(0.99)
    seeds = t_quantile(2, 0.99) * statistics.stdev(xs) / math.sqrt(3)
    boot = quantile(0, 0.99) * math.sqrt((0.03**2 + 0.04**2) / 2)
    assert wide.hi - wide.value == pytest.approx(math.hypot(seeds, boot), rel=1e-9)
    # the print precision's pad is fixed: it is added at every level, not scaled
    padded = iv.widened(0.1, 2.0)
    assert padded.at(0.99).hi - wide.hi == pytest.approx(0.2)
    # a difference of two seed sets keeps both sides' terms
    d = difference([1.0, 1.2, 1.1], [0.5, 0.6, 0.55, 0.52])
    assert len(d.terms) == 2 and d.at(0.99).hi - d.value > d.hi - d.value


def test_holm_steps_down_and_stops() -> None:
    def claim(value: float, half: float) -> Claim:
        # three seeds whose t interval has this half-width
        sd = half * math.sqrt(3) / t_quantile(2)
        return Claim(interval([value - sd, value, value + sd]), 0.0, "<=")

    decisive, borderline, straddling = claim(-10.0, 1.0), claim(-1.2, 1.0), claim(0.5, 1.0)
    assert borderline.verdict() == HOLDS  # at 95 % alone it would hold
    got = holm([straddling, borderline, decisive])
    assert [v for v, _ in got] == [INCONCLUSIVE, INCONCLUSIVE, HOLDS]
    # the decisive claim first at 1 − 0.05 / 3, the borderline one at 1 − 0.05 / 2, then stop
    assert got[2][1] == pytest.approx(1 - 0.05 / 3) and got[1][1] == pytest.approx(0.975)
    # a claim far on the wrong side is decided too; one claim alone is judged at 95 %
    assert [v for v, _ in holm([claim(10.0, 1.0), decisive])] == [NOT_HOLD, HOLDS]
    assert holm([borderline]) == [(HOLDS, 0.95)]
    # a zero-width interval off its bound (nothing detected in any pair) is decided first
    zero = Claim(Interval(0.0, 0.0, 0.0, "exact", ((2, 0.0),)), 0.0, "<=", strict=True)
    assert holm([straddling, zero])[1][0] == NOT_HOLD


def test_holm_keeps_a_family_of_null_parts_at_five_percent() -> None:
    """18 parts (S10's count) whose true values sit on their bounds: any decision is wrong.
    Judged at 95 % each, most families decide something by chance; Holm's procedure keeps the
    families with a wrong decision near 5 %."""
    rng = np.random.default_rng(0)
    families, each, together = 400, 0, 0
    for _ in range(families):
        claims = [Claim(interval(rng.normal(0.0, 1.0, 5)), 0.0, "<=") for _ in range(18)]
        each += any(c.verdict() != INCONCLUSIVE for c in claims)
        together += any(v != INCONCLUSIVE for v, _ in holm(claims))
    assert each / families > 0.5  # 1 − 0.95¹⁸ = 0.60
    assert together / families < 0.09  # 0.05 and its sampling error over 400 families


def test_interval_over_seeds_bootstrap_and_stand_in_by_hand() -> None:
    xs = [1.0, 1.2, 1.1]
    iv = interval(xs)
    half = 4.3027 * statistics.stdev(xs) / math.sqrt(3)
    assert iv.value == pytest.approx(1.1) and iv.hi - iv.value == pytest.approx(half, rel=1e-4)
    assert iv.how == "t over 3 seeds"
    # the bootstrap's part adds in quadrature (root mean square over the seeds)
    both = interval(xs, [0.03, 0.04, None])
    extra = 1.96 * math.sqrt((0.03**2 + 0.04**2) / 2)
    assert both.hi - both.value == pytest.approx(math.hypot(half, extra), rel=1e-3)
    assert "paired bootstrap" in both.how
    # one model: a stand-in seed spread (one draw, not a mean: no √n)
    one = interval([2.0], proxy=(0.1, 5, "the same measurement"))
    assert one.hi - one.value == pytest.approx(2.776 * 0.1 * math.sqrt(1.2), rel=1e-3)
    assert interval([2.0]).lo == interval([2.0]).hi == 2.0
    assert interval([math.nan, None]) is None  # type: ignore[list-item]


def test_paired_bootstrap_standard_error() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 1.0, 400)
    se = bootstrap_se(lambda i: x[i].mean(1), len(x), block=1)
    assert se == pytest.approx(1 / math.sqrt(400), rel=0.1)
    # independent pairs: blocks change little (10 blocks: the estimate itself varies by ~20 %);
    # correlated ones (runs of equal errors) need them: the plain bootstrap underestimates
    assert bootstrap_se(lambda i: x[i].mean(1), len(x)) == pytest.approx(se, rel=0.4)
    walk = np.repeat(rng.normal(0.0, 1.0, 20), 20)  # 20 runs of 20 equal errors
    plain = bootstrap_se(lambda i: walk[i].mean(1), len(walk), block=1)
    assert bootstrap_se(lambda i: walk[i].mean(1), len(walk), block=20) > 2.5 * plain
    # pairing: a difference of two errors sharing their noise has a far smaller error
    y = x + 0.01 * rng.normal(size=400)
    paired = bootstrap_se(lambda i: y[i].mean(1) - x[i].mean(1), len(x), block=1)
    assert paired < se / 20
    assert bootstrap_se(lambda i: i.mean(1), 1) is None


def test_three_outcomes_the_domain_and_the_sentence() -> None:
    def iv(lo: float, hi: float) -> Interval:
        return Interval((lo + hi) / 2, lo, hi)

    assert interval_verdict(iv(0.8, 0.95), 1.0, "<=") == HOLDS
    assert interval_verdict(iv(1.05, 1.2), 1.0, "<=") == NOT_HOLD
    assert interval_verdict(iv(0.9, 1.1), 1.0, "<=") == INCONCLUSIVE
    assert interval_verdict(iv(0.9, 1.1), 0.85, ">=") == HOLDS
    assert interval_verdict(iv(0.5, 0.7), 0.8, ">=") == NOT_HOLD
    # an interval that covers every value the quantity can take decides nothing
    assert interval_verdict(iv(-0.1, 1.2), -0.5, ">=", domain=(0.0, 1.0)) == INCONCLUSIVE
    assert interval_verdict(None, 1.0, "<=") == NO_VERDICT
    # "better than": an interval on the bound does not show it (nothing detected, no motion)
    assert interval_verdict(iv(0.0, 0.0), 0.0, "<=") == HOLDS
    assert interval_verdict(iv(0.0, 0.0), 0.0, "<=", strict=True) == NOT_HOLD
    assert interval_verdict(iv(-0.2, -0.1), 0.0, "<=", strict=True) == HOLDS
    assert interval_verdict(iv(0.0, 0.0), 0.0, ">=", strict=True) == NOT_HOLD
    # widening by the bound's print precision can turn a hold into an inconclusive
    assert interval_verdict(iv(0.9, 0.97).widened(0.05, 1.0), 1.0, "<=") == INCONCLUSIVE
    assert combine([HOLDS, HOLDS]) == HOLDS
    assert combine([HOLDS, NOT_HOLD, INCONCLUSIVE]) == NOT_HOLD
    assert combine([HOLDS, INCONCLUSIVE, NO_VERDICT]) == PARTLY
    assert combine([INCONCLUSIVE, NO_VERDICT]) == INCONCLUSIVE
    assert combine([NO_VERDICT]) == NO_VERDICT


# -- against maintained implementations (statsmodels, arch, SciPy) -----------------------------


@pytest.fixture
def no_full_collections(monkeypatch: pytest.MonkeyPatch) -> None:
    """statsmodels' Holm runs ``gc.collect()`` on every call (a memory precaution for huge
    arrays), 0.1–0.3 s each under the test suite's heap: skipped for these small families."""
    monkeypatch.setattr(gc, "collect", lambda generation=2: 0)


def _dual_p(claim: Claim) -> float:
    """The p-value dual to a claim's interval: the smallest ``α`` at which its interval rebuilt
    at ``1 − α`` is decided (holds or does not hold), by bisection on :meth:`Claim.verdict`."""

    def decided(alpha: float) -> bool:
        return claim.verdict(1 - alpha) in (HOLDS, NOT_HOLD)

    if not claim.iv.terms:  # known at 95 % only (a zero-width difference): decided or not
        return 0.0 if decided(0.05) else 1.0
    lo, hi = 1e-15, 1 - 1e-9
    if decided(lo) or not decided(hi):
        return 0.0 if decided(lo) else 1.0
    for _ in range(80):
        mid = math.sqrt(lo * hi) if hi / lo > 2 else (lo + hi) / 2
        lo, hi = (lo, mid) if decided(mid) else (mid, hi)
    return hi


def _against_statsmodels(claims: list[Claim]) -> None:
    """Our Holm (on intervals) decides what statsmodels' Holm decides on the dual p-values, and
    each decided claim is judged at the level of its rank among the p-values."""
    ps = np.array([_dual_p(c) for c in claims])
    reject = multipletests(ps, alpha=0.05, method="holm")[0]
    ours = holm(claims)
    assert [v in (HOLDS, NOT_HOLD) for v, _ in ours] == list(reject), ps
    rank = {i: r for r, i in enumerate(np.argsort(ps, kind="stable"))}
    for i, (v, level) in enumerate(ours):
        if v in (HOLDS, NOT_HOLD):
            assert level == pytest.approx(1 - 0.05 / (len(claims) - rank[i]))


@pytest.mark.usefixtures("no_full_collections")
def test_holm_decides_what_statsmodels_decides_on_random_families() -> None:
    """Families of 2–18 parts (t over 5 seeds, some true values on their bounds, some off):
    the p-values are the t test's, so statsmodels' ``multipletests(method="holm")`` is the
    textbook procedure our interval form must agree with."""
    rng = np.random.default_rng(11)
    decided = 0
    for _ in range(300):
        m = int(rng.integers(2, 19))
        claims = []
        for _ in range(m):
            shift = rng.choice([0.0, 0.0, 1.5, -2.5, 4.0])
            claims.append(Claim(interval(rng.normal(shift, 1.0, 5)), 0.0, "<="))
        ps = [2 * stats.t.sf(abs(c.iv.value) / c.iv.terms[0][1], 4) for c in claims]
        reject = multipletests(ps, alpha=0.05, method="holm")[0]
        got = [v in (HOLDS, NOT_HOLD) for v, _ in holm(claims)]
        assert got == list(reject)
        decided += sum(got)
    assert decided > 300  # the families decide something: the comparison is not vacuous


def _committed_cached(name: str) -> dict | None:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


@pytest.mark.usefixtures("no_full_collections")
def test_holm_on_the_committed_report_is_statsmodels_holm() -> None:
    """Every family of the committed report (its parts mix t and bootstrap terms, pads and
    strict bounds): statsmodels' Holm on the dual p-values decides the same parts, at the
    levels the report prints."""
    cfg = compose("reproduce", ["poses_dir=unused"])
    views = seed_views(_committed_cached, int(cfg.seed), [int(s) for s in cfg.seeds.extra])
    settled = Settled.load(_committed_cached, cfg)
    families = 0
    for j in judge_all(views, settled, 0.1, 0.8, 0.05):
        claims = [c for p in j.parts if (c := p.claim()) is not None]
        if len(claims) >= 2:
            _against_statsmodels(claims)
            families += 1
    assert families >= 8


@pytest.mark.parametrize(("n", "block"), [(446, 40), (445, 40), (100, 7), (60, 1)])
def test_block_bootstrap_is_archs_moving_block_bootstrap(n: int, block: int) -> None:
    """The same generator gives arch's ``MovingBlockBootstrap`` and ours the same resampled
    pairs (runs of ``block`` from uniform starts, cut to ``n``), so the same standard error."""
    rng = np.random.default_rng(3)
    ref = rng.uniform(0.5, 1.5, n)
    mfg = ref * np.exp(np.cumsum(rng.normal(0.0, 0.1, n)))  # correlated along the sequence
    ours = bootstrap_se(lambda i: np.log(mfg[i].mean(1) / ref[i].mean(1)), n, draws=400,
                        seed=7, block=block)  # fmt: skip
    boot = MovingBlockBootstrap(block, mfg, ref, seed=np.random.default_rng(7))
    theirs = boot.apply(lambda a, b: np.log(a.mean() / b.mean()), 400)
    assert ours == pytest.approx(float(np.std(theirs, ddof=1)), rel=1e-12)


def test_t_quantiles_are_scipys_at_holms_levels() -> None:
    for df in (1, 2, 4, 30):
        for level in (0.95, 0.975, 1 - 0.05 / 18):
            assert t_quantile(df, level) == pytest.approx(stats.t.ppf(1 - (1 - level) / 2, df))


def test_s3_needs_six_seeds_to_decide() -> None:
    """A grid value's interval is the sign test's: three seeds' range covers their median with
    75 % only, so at 95 % the interval is the whole grid (inconclusive); six seeds' covers it
    with 96.9 %."""
    grid = (0.005, 1.0)
    three = median_interval([0.05, 0.01, 0.03], grid)
    assert (three.value, three.lo, three.hi) == (0.03, *grid) and "75.0 %" in three.how
    assert interval_verdict(three, 0.05, "<=", grid) == INCONCLUSIVE
    six = median_interval([0.05, 0.01, 0.03, 0.02, 0.04, 0.03], grid)
    assert (six.lo, six.hi) == (0.01, 0.05) and six.how == (
        "sign test over 6 seeds: order statistics 1 and 6"
    )
    assert interval_verdict(six, 0.05, "<=", grid) == HOLDS
    assert interval_verdict(median_interval([0.1] * 6, grid), 0.05, "<=", grid) == NOT_HOLD
    assert median_interval([math.nan], grid) is None


def test_median_interval_is_what_scipys_sign_test_does_not_reject() -> None:
    rng = np.random.default_rng(5)
    for n in (6, 9, 12, 20, 31):
        xs = rng.normal(size=n)
        iv = median_interval(list(xs), (-10.0, 10.0))
        for b in rng.uniform(-3.0, 3.0, 200):
            p = stats.binomtest(int((xs < b).sum()), n, 0.5).pvalue
            assert (b < iv.lo or b > iv.hi) == (p <= 0.05), (n, b, p)


# -- every sentence on hand-made results --------------------------------------------------------

KS = (1.0, 0.25, 0.2, 0.15, 0.1, 0.05, 0.04, 0.03, 0.02, 0.01, 0.005)
PAIRS = 120


def _main_view(seed: int, good: bool) -> dict:
    """A main-model seed whose values are on the claimed side of every bound (``good``) or on
    the wrong side of every one."""
    j = 1 + 0.01 * seed  # a small spread over seeds
    drop = 1.0 if good else 1.4  # ATE and RPE at k ≤ 5 %, over all units'
    test, val = {}, {}
    for k in KS[:1] + KS[4:]:
        f = 1.0 if k >= 0.1 else (drop if k >= 0.02 else 3.0 * drop)
        if good and k <= 0.03:
            f = 1.1  # the main model needs 4 %: the small set (good) needs more
        test[f"{k:g}"] = {
            "09/ate": 0.01 * f * j,
            "10/ate": 0.01 * f * j,
            "rpe_trans": 0.1 * f * j,
            "rpe_rot": 0.001 * f * j,
        }
        val[f"{k:g}"] = {"ate": 0.02 * (1.0 if (good and k >= 0.05) or k >= 0.1 else 1.5)}
    mfg_growth = (0.9 if good else 9.0) * j

    def bins(growth: float) -> list[dict]:
        return [{"n": 50, "mean": 0.001}, {"n": 50, "mean": 0.001 * growth}]

    methods = {
        "MFG (all units)": mfg_growth,
        "continuous least squares (§3)": 3.0,
        "continuous LS + IRLS (Cauchy)": 3.0,
    }
    residual = [0.05 if good else 0.5] * 20
    decoder = {"residual": residual, "firing_rate": [0.5] * 20}
    return {
        "trained": {},
        "table1": {"test": test, "val": val},
        "methods": {
            "bins": {n: {"rot_bins": bins(g), "trans_bins": bins(g)} for n, g in methods.items()}
        },
        "basis": {
            "per_decoder": {"t": decoder, "omega": decoder},
            "summary": {"t": {"fired": 1.0}, "omega": {"fired": 1.0}},
        },
        "object_motion": None,
    }


def _settled(good: bool) -> Settled:
    rng = np.random.default_rng(0)
    irls = rng.uniform(0.5e-3, 1.5e-3, PAIRS)
    out = Settled()
    for flow in ("exact", "dis"):
        out.classical[flow] = {
            "classical": [
                {"name": "continuous LS + IRLS (Cauchy)", "rot_err": irls.tolist()},
                {"name": "essential matrix + RANSAC", "rot_err": (2 * irls).tolist()},
                {"name": "oracle: exact fields", "rot_err": [0.0] * PAIRS},
            ]
        }
        out.seeds[flow] = {}
        for seed in range(5):
            f = (0.5 if good else 2.0) * (1 + 0.02 * seed)
            mfg = {}
            for k in KS:
                # RPE translation: the small set keeps all units' down to 10 % (good) or 0.5 %
                kept = k >= 0.1 if good else True
                trans = 0.1 * (1.0 if kept else 2.0)
                rot = irls * f * rng.uniform(0.9, 1.1, PAIRS)
                mfg[f"{k:g}"] = {"metrics": {"rpe_trans": trans}, "rot_err": rot.tolist()}
            out.seeds[flow][seed] = {"mfg": mfg, "objects": _objects(good, rng)}
    return out


def _objects(good: bool, rng: np.random.Generator) -> dict:
    """Per-pair mask counts and velocity errors in 2 × 2 bins (the last bin has objects in 3
    pairs only: below the floor)."""
    better, worse = (1.0, 3.0) if good else (3.0, 1.0)
    pixels = np.zeros((PAIRS, 4), dtype=int)
    pixels[:, :3] = rng.integers(5, 20, (PAIRS, 3))
    pixels[:3, 3] = 10

    def method(err: float, tp: int, fp: int) -> dict:
        e = pixels * err * rng.uniform(0.8, 1.2, pixels.shape)
        return {
            "tp": [tp] * PAIRS,
            "fp": [fp] * PAIRS,
            "fn": [50 - tp] * PAIRS,
            "err": e.tolist(),
            "pixels": pixels.tolist(),
        }

    return {
        "size_bins": [0.0, 0.01, 1.0],
        "speed_bins": [0.0, 2.0, 1000.0],
        "pairs": {
            "filters": method(better, 40 if good else 20, 5 if good else 30),
            "threshold": method(worse, 30, 20),
            # reporting no motion costs the objects' speed: 2 px a pixel
            "speed": (pixels * 2.0).tolist(),
        },
    }


@pytest.mark.parametrize("good", [True, False])
def test_every_sentence_can_hold_and_can_fail(good: bool) -> None:
    """Done when of issue 44: with the report's own bounds, values on the wrong side of every
    bound give "does not hold" or "inconclusive" for every part of S1–S10, and values on the
    claimed side hold (so the verdict follows the values, not the rule)."""
    # six main seeds: S3's sign test places a median at 95 % from six values on (three seeds'
    # range covers it with 75 % at most: test_s3_needs_six_seeds_to_decide)
    views = {s: _main_view(s, good) for s in range(6)}
    judged = {j.sentence.key: j for j in judge_all(views, _settled(good), 0.1, 0.8, 0.05)}
    assert sorted(judged, key=lambda k: int(k[1:])) == [f"S{i}" for i in range(1, 11)]
    for key, j in judged.items():
        assert j.parts, key
        for p in j.parts:
            if key == "S10" and "below the floor" in p.floor:
                assert p.verdict == INCONCLUSIVE  # a bin not measured: no wide range shown
            elif good:
                assert p.verdict == HOLDS, (key, p.text())
            else:
                assert p.verdict in (NOT_HOLD, INCONCLUSIVE), (key, p.text())
        # S10 has a bin without objects: it cannot hold whole
        expected = (PARTLY if key == "S10" else HOLDS) if good else NOT_HOLD
        assert j.verdict == expected, (key, j.verdict)


def test_s5_prints_the_one_tolerance_reading_beside_its_verdict() -> None:
    """S5's verdict reads each model within its own table's print precision (stated before the
    2 × 2 was trained); the reading with Table 1's ±8.3 % on both sides is printed beside with
    its own interval and verdict, which here differ from the verdict's."""
    views = {s: _main_view(s, True) for s in range(3)}  # the main model's k: 4 %
    settled = _settled(True)
    for r in settled.seeds["exact"].values():
        # within Table 1's ±8.3 % of all units' at 5 % and 4 %, not within Table 2's ±0.06 %
        for k in ("0.05", "0.04"):
            r["mfg"][k]["metrics"]["rpe_trans"] = 0.1 * 1.05
    s5 = next(j for j in judge_all(views, settled, 0.1, 0.8, 0.05) if j.sentence.key == "S5")
    (part,) = s5.parts
    assert s5.verdict == HOLDS and part.value == pytest.approx(2.5)  # 10 % over 4 %
    assert "on both sides (beside, not the verdict) the small set's k are 4 %" in part.note
    assert part.note.endswith("the ratio ×1.000 [×1.000, ×1.000]: does not hold on that reading")
