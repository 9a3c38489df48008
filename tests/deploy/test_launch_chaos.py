"""Chaos faults: checked against the run before anything starts, described in words, garbage that
never decodes; and the `semfleet launch`/`chaos` mistakes of issue 12, each one line and exit 2
with nothing written."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from agents.links import Partition
from deploy.cli.main import main
from deploy.launch import Faults, LaunchPlan, PlanError, garbage_stack
from protocol.codec import decode
from protocol.errors import RemoteProtocolError
from sim.loader import load_scenario

PAPER = load_scenario("paper")
ROBOTS = ("r1", "r2", "r3")


def test_faults_schedule_keeps_every_fault_of_a_step_kills_first() -> None:
    faults = Faults(kills=(("r2", 5), ("r1", 5)), restarts=(("r2", 5), ("r1", 7)))
    assert faults.schedule() == [
        (5, "kill", "r1"),
        (5, "kill", "r2"),
        (5, "restart", "r2"),
        (7, "restart", "r1"),
    ]
    faults.check(ROBOTS, 12, lockstep=False)


@pytest.mark.parametrize(
    ("faults", "lockstep", "message"),
    [
        (Faults(partitions=(Partition(frozenset({"r9"}), 1, 3),)), False,
         "partition r9:1-3: no robot r9 in this run (r1, r2, r3)"),
        (Faults(partitions=(Partition(frozenset({"r1"}), 1, 99),)), False,
         "partition r1:1-99: steps outside the run's 1..12"),
        (Faults(partitions=(Partition(frozenset({"r1"}), 0, 3),)), False,
         "partition r1:0-3: steps outside the run's 1..12"),
        (Faults(kills=(("r1", 99),)), False, "kill r1@99: step outside the run's 1..12"),
        (Faults(kills=(("r1", 0),)), False, "kill r1@0: step outside the run's 1..12"),
        (Faults(kills=(("r9", 3),)), False, "kill r9@3: no robot r9 in this run"),
        (Faults(kills=(("r1", 5),), restarts=(("r1", 3),)), False,
         "restart r1@3: a restart needs an earlier kill of r1"),
        (Faults(restarts=(("r2", 3),)), False,
         "restart r2@3: a restart needs an earlier kill of r2"),
        (Faults(kills=(("r1", 5), ("r1", 7))), False,
         "kill r1@7: r1 is down since its kill at step 5"),
        (Faults(kills=(("r1", 5),), restarts=(("r1", 6), ("r1", 8))), False,
         "restart r1@8: a restart needs an earlier kill of r1"),
        # lock-step: the next round waits for every robot, so a killed one restarts at once
        (Faults(kills=(("r2", 5),), restarts=(("r2", 6),)), True,
         "restart r2@6: in lock-step a killed robot restarts at its kill step"),
        (Faults(kills=(("r2", 5),)), True,
         "kill r2@5: in lock-step a killed robot restarts at its kill step"),
    ],
)  # fmt: skip
def test_faults_check_refuses_what_the_run_cannot_do(
    faults: Faults, lockstep: bool, message: str
) -> None:
    with pytest.raises(PlanError) as info:
        faults.check(ROBOTS, 12, lockstep)
    assert str(info.value).startswith(message), str(info.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"drop": 1.5}, "drop 1.5: a probability"), ({"garbage_rate": float("nan")}, "garbage nan")],
)
def test_faults_refuse_impossible_rates(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(PlanError, match=message):
        Faults(**kwargs)  # type: ignore[arg-type]


def test_launch_plan_checks_its_faults_and_robots(tmp_path: Path) -> None:
    with pytest.raises(PlanError, match="restart r2@3: a restart needs an earlier kill"):
        LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path, faults=Faults(restarts=(("r2", 3),)))
    with pytest.raises(PlanError, match=r"kill r1@13: step outside the run's 1\.\.12"):
        LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path, steps=12, faults=Faults(kills=(("r1", 13),)))
    with pytest.raises(PlanError, match="robots: r1 listed more than once"):
        LaunchPlan(PAPER, 0, ["r1", "r2", "r1"], tmp_path)
    with pytest.raises(PlanError, match=r"linger 5\.0: needs observe_stacks"):
        LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path, linger=5.0)
    assert not any(tmp_path.iterdir())


def test_faults_describe_is_words_not_python() -> None:
    faults = Faults(
        0.2,
        (Partition(frozenset({"r2", "r1"}), 5, 10),),
        (("r2", 5),),
        (("r2", 7),),
        50.0,
    )
    assert faults.describe() == (
        "drop 0.2, partition r1,r2:5-10, kill r2@5, restart r2@7, garbage 50 stacks/s"
    )
    assert Faults().describe() == "drop 0, garbage 0 stacks/s"


def test_garbage_stacks_never_decode() -> None:
    rng = random.Random(7)
    for _ in range(300):
        with pytest.raises(RemoteProtocolError):
            decode(garbage_stack(rng))


# --------------------------------------------------------------------------- the commands


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["launch", "--robots", "r1,r1"], "robots: r1 listed more than once"),
        (["chaos", "--garbage", "-1"], "garbage -1: stacks per second need a rate ≥ 0"),
        (["chaos", "--partition", "r9:1-3"], "partition r9:1-3: no robot r9 in this run"),
        (["chaos", "--partition", "r1:1-99"], "partition r1:1-99: steps outside the run's 1..60"),
        (["chaos", "--kill", "r1@99"], "kill r1@99: step outside the run's 1..60"),
        (["chaos", "--steps", "12", "--kill", "r1@13"], "kill r1@13: step outside the run's 1..12"),
        (["chaos", "--kill", "r1@5", "--restart", "r1@3"], "restart r1@3: a restart needs an"),
        (["chaos", "--restart", "r2@3"], "restart r2@3: a restart needs an earlier kill of r2"),
    ],
)
def test_launch_and_chaos_mistakes_are_one_line_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], fragment: str
) -> None:
    out = tmp_path / "out"
    code = main([args[0], "--scenario", "paper", *args[1:], "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 2, captured
    assert captured.err.startswith("semfleet: error: ") and captured.err.count("\n") == 1
    assert fragment in captured.err, captured.err
    assert captured.out == ""  # not even the launch's header
    assert not out.exists()


def test_launch_plan_topology_is_mesh_or_a_plain_loopback_router(tmp_path: Path) -> None:
    assert LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path).topology == "mesh"
    LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path, topology="router")
    with pytest.raises(PlanError, match="topology 'star'"):
        LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path, topology="star")
    for kwargs in ({"secure": True}, {"zenoh_neighbours": {"r1": ["r2"]}}):
        with pytest.raises(PlanError, match="topology router: a plain loopback launch only"):
            LaunchPlan(PAPER, 0, list(ROBOTS), tmp_path, topology="router", **kwargs)  # type: ignore[arg-type]
