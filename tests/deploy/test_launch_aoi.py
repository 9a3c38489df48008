"""The age of information of a launch (deploy/launch/aoi.py; docs/results.md): the computation on
hand-made logs with known answers, the hop counts, and a realtime launch of agent processes that
archives it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from deploy.launch.aoi import (
    UNLINKED,
    AgeOfInformation,
    age_of_information,
    holding_gaps,
    hop_counts,
    link_hops,
    senders_to_receivers,
    undirected,
)
from sim.line_world import line_world
from tests.tolerance import assert_close

SEMFLEET = Path(sys.executable).with_name("semfleet")
LINE = ("a", "b", "c")


def _line_hops(owner: str, receiver: str, k: int) -> int:
    return abs(LINE.index(owner) - LINE.index(receiver))


def test_holding_gaps_compare_the_oldest_fused_version_with_the_host_clock() -> None:
    """c's estimate of step 4 arrived at 10.9 s and fused a's 3 (ended 10.0) and b's 4 (10.5):
    its oldest peer version is 900 ms old by the clock; c said 880 (transits left out): −20 ms.
    b's estimate of 4 fused a's 2, whose end is not known: left out; a said nothing."""
    ended = {("a", 3): 10.0, ("b", 4): 10.5, ("a", 4): 10.6}
    fused = [
        (10.9, "c", 4, {"a": 3, "b": 4, "c": 4}),
        (10.7, "b", 4, {"a": 2, "b": 4}),
        (10.8, "a", 4, {"b": 4}),
    ]
    said = [(10.9, "c", 4, 880), (10.7, "b", 4, 700)]
    assert_close(holding_gaps(ended, fused, said), [-20.0], atol=1e-9)
    assert holding_gaps(ended, fused, []).size == 0


def _ages(r: AgeOfInformation) -> dict[tuple[str, str, int], tuple[float, int]]:
    return {
        (o, i, int(k)): (float(a), int(h))
        for o, i, k, a, h in zip(r.owner, r.receiver, r.step, r.age_s, r.hops, strict=True)
    }


def test_age_is_first_fused_report_minus_the_end_of_the_step() -> None:
    """a ends steps 1, 2, 3 at 10, 11, 12 s. b reports a's version 1 at 10.4 s, then a's version 3
    at 12.5 s (it never fused version 2: version 3 carries it). c reports version 1 only at
    11.9 s (a report of version 0 before does not count) and nothing newer: a's steps 2 and 3
    never reached c."""
    ended = {("a", 1): 10.0, ("a", 2): 11.0, ("a", 3): 12.0}
    fused = [
        (12.5, "b", 3, {"a": 3}),  # out of order: sorted by time
        (10.4, "b", 1, {"a": 1}),
        (11.2, "b", 2, {"a": 1}),  # no newer version: nothing first
        (10.9, "c", 1, {"a": 0}),
        (11.9, "c", 2, {"a": 1, "c": 9}),  # its own stamp is no peer's
    ]
    got = age_of_information(LINE, ended, fused, _line_hops)
    ages = _ages(got)
    assert sorted(ages) == [("a", "b", 1), ("a", "b", 2), ("a", "b", 3), ("a", "c", 1)]
    for key, (age, hops) in {
        ("a", "b", 1): (0.4, 1),
        ("a", "b", 2): (1.5, 1),
        ("a", "b", 3): (0.5, 1),
        ("a", "c", 1): (1.9, 2),
    }.items():
        assert_close(ages[key][0], age)
        assert ages[key][1] == hops
    assert got.unreached == 3 * 2 - 4  # (a, c, 2) and (a, c, 3)


def test_age_counts_only_the_robots_of_the_run_and_steps_that_ended() -> None:
    """Reports of a robot outside ``robots`` are not timed; a stamp whose end is unknown (its
    owner skipped that estimate while catching up) is passed over, not guessed."""
    ended = {("a", 2): 5.0}
    fused = [(5.5, "b", 1, {"a": 3}), (5.6, "zz", 1, {"a": 3})]
    got = age_of_information(("a", "b"), ended, fused, lambda o, r, k: 1)
    assert _ages(got).keys() == {("a", "b", 2)}
    assert_close(got.age_s, np.array([0.5]))
    assert got.unreached == 0


def test_age_document_gives_figures_overall_and_per_hop_count() -> None:
    ended = {("a", k): float(k) for k in range(1, 101)}
    fused = [(k + 0.01 * k, "b", k, {"a": k}) for k in range(1, 101)]
    fused += [(k + 0.5, "c", k, {"a": k}) for k in range(1, 51)]
    doc = age_of_information(LINE, ended, fused, _line_hops).document()
    assert doc["samples"] == 150 and doc["unreached"] == 50
    assert list(doc["by_hops"]) == ["1", "2"]
    one, two = doc["by_hops"]["1"], doc["by_hops"]["2"]
    assert one["samples"] == 100 and two["samples"] == 50
    assert_close(one["max_ms"], 1000.0)
    assert_close(one["p50_ms"], float(np.percentile(10.0 * np.arange(1, 101), 50)))
    assert_close(two["p99_ms"], 500.0)
    assert_close(doc["max_ms"], 1000.0)
    json.dumps(doc, allow_nan=False)  # strict JSON, as results.json


def test_age_arrays_index_the_robots_of_the_run() -> None:
    ended = {("c", 4): 1.0}
    got = age_of_information(LINE, ended, [(1.25, "a", 4, {"c": 4})], _line_hops)
    arrays = got.arrays(LINE)
    assert_close(arrays["aoi/age_ms"], np.array([250.0]))
    assert [arrays[k].tolist() for k in ("aoi/hops", "aoi/owner", "aoi/receiver", "aoi/step")] == [
        [2],
        [2],
        [0],
        [4],
    ]
    assert {a.dtype.kind for k, a in arrays.items() if k != "aoi/age_ms"} == {"i"}


def test_age_without_samples_has_null_figures_and_says_so() -> None:
    got = age_of_information(LINE, {("a", 1): 1.0}, [], _line_hops)
    doc = got.document()
    assert (doc["samples"], doc["p99_ms"], doc["unreached"], doc["by_hops"]) == (0, None, 2, {})
    assert "no version timed" in got.line()


def test_unlinked_pairs_are_their_own_bucket_after_the_hop_counts() -> None:
    ended = {("a", 1): 0.0}
    fused = [(1.0, "b", 1, {"a": 1}), (2.0, "c", 1, {"a": 1})]
    doc = age_of_information(
        LINE, ended, fused, lambda o, r, k: UNLINKED if r == "b" else 3
    ).document()
    assert list(doc["by_hops"]) == ["3", "unlinked"]


def test_hop_counts_follow_the_links_in_force_and_the_zenoh_topology() -> None:
    chain = {"a": ["b"], "b": ["a", "c"], "c": ["b"]}
    assert hop_counts(undirected({"a": ["b"], "c": ["b"]}), "a") == {"a": 0, "b": 1, "c": 2}
    # Step 1: everyone hears everyone; step 2: c hears b, b hears nobody (a one-way link).
    verdicts: dict[int, dict[str, tuple[str, ...]]] = {
        1: {"a": ("b", "c"), "b": ("a", "c"), "c": ("a", "b")},
        2: {"a": (), "b": (), "c": ("b",)},
    }
    asked: list[int] = []

    def links(k: int) -> dict[str, tuple[str, ...]]:
        asked.append(k)
        return verdicts[k]

    mesh = link_hops(links, LINE)
    assert mesh("a", "c", 1) == 1 and mesh("a", "c", 2) == UNLINKED and mesh("b", "c", 2) == 1
    assert mesh("c", "b", 2) == UNLINKED
    assert asked == [1, 2]  # each step's counts made once
    on_chain = link_hops(links, LINE, chain)  # Zenoh joins only neighbours: a–c goes over b
    assert on_chain("a", "c", 1) == 2 and on_chain("c", "a", 1) == 2
    assert senders_to_receivers(verdicts[2]) == {"b": {"c"}}


@pytest.mark.slow
def test_launch_archives_the_age_of_information_of_its_agents(tmp_path: Path) -> None:
    """Three agent processes on a line (range 10 m, 8 m apart: neighbours hear each other only),
    realtime: the launch prints the age of information and writes it to results.json, measured
    from the agents' ``fused`` maps; every timed pair is one or two hops apart, and the
    figures are ordered. No time is asserted: the machine decides them."""
    world = tmp_path / "line3.toml"
    world.write_text(line_world(3, steps=8), encoding="utf-8")
    args = ["--scenario", str(world), "--mode", "realtime", "--period", "0.3"]
    r = subprocess.run(
        [str(SEMFLEET), "launch", *args, "--out", str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=600,  # a guard against hangs
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "age of information over" in r.stdout, r.stdout[-3000:]
    doc = json.loads((tmp_path / "run" / "results.json").read_text(encoding="utf-8"))
    aoi = doc["launch"]["aoi"]
    assert aoi["samples"] > 0, aoi
    assert set(aoi["by_hops"]) <= {"1", "2"} and "1" in aoi["by_hops"], aoi
    assert sum(f["samples"] for f in aoi["by_hops"].values()) == aoi["samples"]
    assert aoi["p50_ms"] <= aoi["p99_ms"] <= aoi["max_ms"], aoi
    # Every estimate of every step that reached the conductor is either timed at both peers
    # or counted as never fused: at most 8 steps × 3 robots × 2 peers.
    assert aoi["samples"] + aoi["unreached"] <= 8 * 3 * 2
    with np.load(tmp_path / "run" / "results.npz") as npz:
        age, hops = npz["aoi/age_ms"], npz["aoi/hops"]
        owner, receiver, step = npz["aoi/owner"], npz["aoi/receiver"], npz["aoi/step"]
    assert age.shape == hops.shape == step.shape == (aoi["samples"],)
    assert round(float(age.max()), 3) == aoi["max_ms"]  # results.json: to the µs
    assert np.array_equal(hops, np.abs(owner - receiver))  # the line: |i − j| hops
    assert ((step >= 1) & (step <= 8)).all()
