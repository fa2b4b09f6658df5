"""The report's learned-flow section (:mod:`mfg_lightning.study.causes`) and its convergence
figure (:func:`mfg_lightning.study.claims.convergence_rows`) on hand-made results: the table
reads each model's own scores, the one learned-flow training is placed against the range of the
main model's seeds, and the figure groups each setting's seeds in a panel of its family."""

from __future__ import annotations

from mfg_lightning.study.causes import learned_section


def _scores(ate: float, central: float, rot: float) -> dict:
    return {"09/ate": ate, "09/ate_central": central, "10/ate": ate, "10/ate_central": central,
            "rpe_rot": rot}  # fmt: skip


def _flow_error(all_: float, road: float, far: float) -> dict:
    regions = {"all": {"epe": all_}, "road": {"epe": road}, "far": {"epe": far}}
    return {"test": {"1": {"regions": regions}, "2": {"regions": regions}}}


def test_the_learned_section_places_one_training_against_the_seed_range() -> None:
    views = {
        0: {"table1": {"test": {"1": _scores(0.020, 0.040, 0.0014)}}},
        1: {"table1": {"test": {"1": _scores(0.022, 0.044, 0.0016)}}},
    }
    learned = {
        "steps": 900,
        "convergence": {"converged": True},
        "table1": {"test": {"1": _scores(0.021, 0.030, 0.0017)}},
        "dis_test": _scores(0.03, 0.2, 0.0018),
        "flow_error": _flow_error(2.5, 2.9, 1.3),
    }
    text = "\n".join(learned_section(views, None, learned, _flow_error(5.4, 9.1, 1.27)))
    rows = [line for line in text.splitlines() if line.startswith("| MFG")]
    assert rows[0].split("|")[4:8] == [" 5.40 ", " 5.40 ", " 9.10 ", " 1.27 "]
    assert rows[1].split("|")[4:8] == [" 2.50 ", " 2.50 ", " 2.90 ", " 1.30 "]
    assert "ATE † 09 0.0210 is within their 0.0200–0.0220" in text
    assert "ATE * 09 0.0300 is better than their 0.0400–0.0440" in text
    assert "RPE rotation 0.00170 is worse than their 0.00140–0.00160" in text
    assert "the RPE translation of the learned-flow model is not measured;" in text
    # one main seed has no range to place it in
    one = learned_section({0: views[0]}, None, learned, None)
    assert not any("range" in line for line in one)
    assert learned_section(views, None, None, None) == []


def test_the_convergence_figure_groups_seeds_and_never_repeats_a_colour_in_a_panel() -> None:
    from matplotlib.colors import to_hex

    from mfg_lightning.study.figures import convergence_rows

    def model(steps: int, ates: list[float]) -> dict:
        curve = [{"step": 1000 * (i + 1), "samples": 16000 * (i + 1), "val/ate": a}
                 for i, a in enumerate(ates)]  # fmt: skip
        return {"steps": steps, "samples_seen": 16 * steps, "curve": curve,
                "convergence": {"converged": True, "decay_start": steps - 1000,
                                "decay_end": steps}}  # fmt: skip

    models = {"main": model(2000, [0.03, 0.02]), "main, seed 1": model(2000, [0.04, 0.02])}
    models |= {f"table2 exact, seed {s}": model(2000, [0.02, 0.01]) for s in range(5)}
    models |= {f"sparsity w_s={w}": model(2000, [0.05, 0.03]) for w in range(12)}
    rows, fig = convergence_rows(models)
    assert len(rows) == len(models)
    panels = {ax.get_title(): ax for ax in fig.axes if ax.get_visible()}
    assert list(panels) == ["main setting", "Table 2 setting", "sparsity, recipe"]
    legend = [t.get_text() for t in panels["main setting"].get_legend().get_texts()]
    assert legend == ["main (2)"]
    assert [t.get_text() for t in panels["Table 2 setting"].get_legend().get_texts()] == [
        "table2 exact (5)"
    ]
    # a setting's seeds are one group: one colour, one line each
    main_colours = {to_hex(line.get_color()) for line in panels["main setting"].get_lines()}
    assert len(main_colours) == 1 and len(panels["main setting"].get_lines()) == 2


def test_the_convergence_table_gives_the_best_value_of_the_metric_the_rule_watched() -> None:
    from mfg_lightning.study.figures import convergence_rows

    curve = [{"step": 1000, "samples": 16000, "val/ate": 0.03, "val/rot_err": 0.004},
             {"step": 2000, "samples": 32000, "val/ate": 0.02, "val/rot_err": 0.005}]  # fmt: skip
    rule = {"converged": True, "decay_start": 1000, "decay_end": 2000}
    models = {
        "ate rule": {"steps": 2000, "curve": curve, "convergence": rule},
        "rotation rule": {"steps": 2000, "curve": curve,
                          "convergence": {**rule, "rule": {"monitor": "val/rot_err"}}},
    }  # fmt: skip
    rows, _ = convergence_rows(models)
    assert rows[0][4] == "0.0200 (val/ate)" and rows[1][4] == "0.00400 (val/rot_err)"
