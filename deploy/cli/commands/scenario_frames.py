"""`semfleet scenario frames NAME --seed S --robot ID -o FILE.jsonl`: one robot's simulated frames
as a frame log (docs/wire.md, "Frame logs"), what that robot's logger would have written. The log
holds no ground truth: ``protocol.framelog`` never writes it. ``--ids none|local|global``,
``--clutter R`` and ``--miss P`` make the detector a real one (``sim.sensors.Detector``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.base.files import write_text_atomically
from deploy.cli.args import add_detector_arguments, detector_from_args, positive_int, seed
from deploy.cli.outputs import add_force, new_file
from deploy.cli.scenario_args import add_scenario_arguments, scenario_from_args
from protocol.framelog import format_frame_line, format_header
from sim.scenario import Scenario, ScenarioError
from sim.sensors import Detector, Simulator


def frame_log_lines(
    scenario: Scenario,
    seed: int,
    robot: str,
    steps: int | None = None,
    detector: Detector | None = None,
) -> list[str]:
    """The log of ``robot``'s frames k = 1..``steps`` (default: all) under ``seed``, as
    ``detector`` (default: global ids, no clutter, no misses) delivers them: the header, then
    one line per frame, without newlines."""
    if robot not in scenario.robot_ids:
        known = ", ".join(scenario.robot_ids)
        raise ScenarioError(f"--robot: {robot!r} is not a robot of {scenario.name} ({known})")
    last = scenario.steps if steps is None else steps
    if not 1 <= last <= scenario.steps:
        raise ScenarioError(
            f"--steps {last}: outside 1..{scenario.steps} (scenario {scenario.name})"
        )
    sim = Simulator(scenario, seed, detector=detector)
    frames = [sim.frame(robot, k) for k in range(1, last + 1)]
    return [format_header(), *(format_frame_line(f) for f in frames)]


def run(args: argparse.Namespace, console: Console) -> int:
    out = new_file(Path(args.output), "--output", args.force)
    scenario = scenario_from_args(args)
    detector = detector_from_args(args)
    lines = frame_log_lines(scenario, args.seed, args.robot, args.steps, detector)
    write_text_atomically(out, "".join(line + "\n" for line in lines))
    faults = "" if detector.exact else f", ids {args.ids}, clutter {args.clutter}, miss {args.miss}"
    if detector.confirmable is not None:
        faults += ", confirmable detections only"
    console.print(
        f"wrote {out}: {len(lines) - 1} frames of {args.robot} ({scenario.name}, seed {args.seed}"
        f"{faults})"
    )
    return 0


def add_parser(ssub: Any) -> None:
    """Register ``frames`` under the ``scenario`` subcommands ``ssub``."""
    p = ssub.add_parser("frames", help="a robot's simulated frames as a JSON-lines log, no truth")
    add_scenario_arguments(p)
    p.add_argument("--seed", type=seed, required=True, help="the sensor noise seed")
    p.add_argument("--robot", required=True, help="whose frames (a robot of the scenario)")
    p.add_argument("--steps", type=positive_int, default=None, help="only frames 1..N")
    add_detector_arguments(p)
    p.add_argument("-o", "--output", required=True, help="the log to write (.jsonl)")
    add_force(p)
    p.set_defaults(run=run)
