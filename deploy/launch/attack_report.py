"""What ``semfleet chaos --attack`` runs and prints: one lock-step launch per attack against a
fleet (secure with ``--secure``), each compared with the clean run (:mod:`deploy.launch.attack_run`,
docs/deploy.md), and the table of what each attack achieved."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from deploy.base.errors import UsageError
from deploy.base.output import figures_table
from deploy.launch import LaunchPlan
from deploy.launch.attack_run import AttackReport, run_each
from deploy.launch.attacks import parse_attacks
from sim.loader import load_scenario


def attack_list(text: str) -> tuple[str, ...]:
    try:
        return parse_attacks(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def run_attacks_command(args: argparse.Namespace, console: Console) -> int:
    """``chaos --attack``: one lock-step launch per attack, each compared with the clean run."""
    others = {
        "--drop": args.drop,
        "--partition": args.partition,
        "--kill": args.kill,
        "--restart": args.restart,
        "--garbage": args.garbage,
    }
    used = [name for name, value in others.items() if value]
    if used or args.net != "loopback":
        used += ["--net"] if args.net != "loopback" else []
        raise UsageError(f"--attack: not with {', '.join(used)} (attacks run on a clean fleet)")
    scenario = load_scenario(args.scenario)
    steps = args.steps
    if steps is not None and steps > scenario.steps:
        raise UsageError(f"--steps: {steps} outside 1..{scenario.steps} (scenario {scenario.name})")
    if (steps or scenario.steps) < 3:
        raise UsageError("--attack: needs at least 3 steps (attacks act between steps)")
    fleet = "a secure fleet" if args.secure else "an insecure fleet (no --secure)"
    console.print(
        f"attacks on {fleet} of {scenario.name}, seed {args.seed}: {', '.join(args.attack)} "
        "(lock-step, one run per attack, each compared with the clean run)"
    )

    def plan_for(attack: str) -> LaunchPlan:
        return LaunchPlan(
            scenario,
            args.seed,
            list(scenario.robot_ids),
            Path(args.out) / attack,
            mode="lockstep",
            comm=args.comm,
            steps=steps,
            secure=args.secure,
        )

    reports = run_each(plan_for, args.attack)
    for line in sessions_lines(reports):
        console.print(f"- {line}")
    headings = ["attack", "achieved", "agents counted", "same as clean"]
    title = f"what each attack achieved on {fleet}"
    console.print(figures_table(title, headings, attack_rows(reports), text=(1, 2)))
    return 0


def attack_rows(reports: Sequence[AttackReport]) -> list[list[str]]:
    """One row per attack of each report (one fleet, named in the title): the attack, what it
    achieved, what the agents counted, and whether every estimate equals the clean run's."""
    rows = []
    for rep in reports:
        for a in rep.achieved:
            achieved = "; ".join(a.effects) if a.effects else "[green]nothing[/]"
            if rep.differing and not a.effects and len(rep.achieved) == 1:
                achieved = "[red]estimates changed[/]"
            same = f"{rep.compared - len({(r, k) for r, k, _ in rep.differing})}/{rep.compared}"
            if rep.stopped_early:
                same += f" (ended at {max(rep.last_step.values(), default=0)})"
            rows.append([a.attack, achieved, a.counted, same])
    return rows


def sessions_lines(reports: Sequence[AttackReport]) -> list[str]:
    """How each attacker session fared, once per fleet (the same in every run of a fleet)."""
    lines: dict[str, str] = {}
    for rep in reports:
        for label, state in rep.connected.items():
            lines.setdefault(f"{rep.fleet} fleet, {label}", state)
    return [f"{who}: {state}" for who, state in lines.items()]
