"""`semfleet study --paper` (issue 41, item 3): the paper's read-off values against a study's
means, in a table, in paper.json and on the plots; refused in one line for any other world."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from deploy.cli.main import main
from deploy.study.paper_figures import (
    PAPER_VALUES,
    READING,
    Comparison,
    PaperValue,
    by_metric,
    compare,
    paper_world_error,
    values_for,
)

METHODS = ("local", "distributed", "double_count")


def _doc(steps: int, curves: dict[str, dict[str, list[float | None]]]) -> dict[str, Any]:
    return {"steps": steps, "methods": {m: {"mean": c} for m, c in curves.items()}}


def test_the_read_off_values_are_the_ones_docs_paper_quotes() -> None:
    got = {(v.figure, v.metric, v.method, v.step): (v.low, v.high) for v in PAPER_VALUES}
    point = {
        ("Fig. 3a", "msde", "local", 60): 0.09,
        ("Fig. 2b", "robot_error", "local", 60): 0.62,
        ("Fig. 2d", "robot_sqrt_det", "local", 60): 0.03,
        ("Fig. 2d", "robot_sqrt_det", "distributed", 60): 0.009,
        ("Fig. 2d", "robot_sqrt_det", "double_count", 60): 0.006,
    }
    for key, value in point.items():
        assert got.pop(key) == pytest.approx((value * (1 - READING), value * (1 + READING)))
    assert got == {
        ("Fig. 3a", "msde", "distributed", 60): (0.01, 0.02),
        ("Fig. 3a", "msde", "double_count", 60): (0.02, 0.03),
    }


def test_a_value_holds_inside_its_interval_only() -> None:
    v = PaperValue("Fig. 3a", "msde", "distributed", 60, 0.01, 0.02)
    assert v.middle == pytest.approx(0.015)
    assert [v.holds(x) for x in (0.0099, 0.01, 0.015, 0.02, 0.0201)] == [
        False,
        True,
        True,
        True,
        False,
    ]


def test_compare_reads_each_methods_mean_at_the_values_step() -> None:
    steps = 60
    # a distinct number at every step and method, so that an off-by-one or a swapped method
    # reads the wrong one
    curves = {
        m: {
            "msde": [0.001 * k + i for k in range(1, steps + 1)],
            "robot_error": [0.5 + i + 0.01 * k for k in range(1, steps + 1)],
            "robot_sqrt_det": [None] * (steps - 1) + [float("nan")],
        }
        for i, m in enumerate(METHODS)
    }
    rows = {(r.value.metric, r.value.method): r for r in compare(_doc(steps, curves))}
    assert len(rows) == len(PAPER_VALUES)
    local = rows[("msde", "local")]
    assert local.ours == pytest.approx(0.060)
    assert local.ratio == pytest.approx(0.060 / 0.09)
    assert local.holds is False
    assert rows[("msde", "distributed")].ours == pytest.approx(1.060)
    assert rows[("robot_error", "local")].ours == pytest.approx(1.1)
    # not scored, or not a number: no figure, no verdict
    assert rows[("robot_sqrt_det", "local")].ours is None
    assert rows[("robot_sqrt_det", "local")].holds is None
    within = Comparison(rows[("msde", "distributed")].value, 0.012)
    assert within.holds is True and within.document()["within"] is True


def test_only_methods_the_study_ran_and_steps_it_has_are_compared() -> None:
    short = _doc(30, {"local": {"msde": [0.1] * 30}})
    assert values_for(short) == []  # every value is at k = 60
    one = _doc(60, {"distributed": {"msde": [0.1] * 60}})
    assert {v.method for v in values_for(one)} == {"distributed"}
    assert {v.metric for v in values_for(one)} == {"msde", "robot_sqrt_det"}
    # a metric the document lacks: compared as not scored
    assert [r.ours for r in compare(one) if r.value.metric == "robot_sqrt_det"] == [None]
    grouped = by_metric(PAPER_VALUES)
    assert sorted(grouped) == ["msde", "robot_error", "robot_sqrt_det"]
    assert len(grouped["robot_sqrt_det"]) == 3


def test_only_the_paper_world_is_compared() -> None:
    assert paper_world_error("paper") is None
    why = paper_world_error("lanes")
    assert why is not None and "'lanes'" in why and "'paper'" in why


def test_study_paper_writes_the_comparison_and_refuses_other_worlds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "paper"
    argv = ["study", "--scenario", "paper", "--methods", "local,distributed", "--runs", "1"]
    assert main([*argv, "--jobs", "1", "--out", str(out), "--paper"]) == 0
    printed = capsys.readouterr().out
    assert "read off the paper's figures" in printed
    results = json.loads((out / "results.json").read_text(encoding="utf-8"))
    doc = json.loads((out / "paper.json").read_text(encoding="utf-8"))
    assert "RA-L 2020" in doc["source"]
    rows = doc["rows"]
    assert {(r["method"], r["metric"]) for r in rows} == {
        ("local", "msde"),
        ("distributed", "msde"),
        ("local", "robot_error"),
        ("local", "robot_sqrt_det"),
        ("distributed", "robot_sqrt_det"),
    }
    for r in rows:
        ours = results["methods"][r["method"]]["mean"][r["metric"]][r["step"] - 1]
        assert r["ours"] == ours and math.isfinite(ours)
        assert r["ratio"] == pytest.approx(ours / ((r["paper_low"] + r["paper_high"]) / 2))
        assert r["within"] == (r["paper_low"] <= ours <= r["paper_high"])
    assert (out / "msde.png").read_bytes()[:4] == b"\x89PNG"

    plain = tmp_path / "plain"
    assert main([*argv, "--jobs", "1", "--out", str(plain)]) == 0
    assert not (plain / "paper.json").exists()
    assert "read off" not in capsys.readouterr().out

    assert (
        main(
            ["study", "--scenario", "lanes", "--runs", "1", "--paper", "--out", str(tmp_path / "x")]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'lanes'" in err
    assert not (tmp_path / "x").exists()  # refused before any run
