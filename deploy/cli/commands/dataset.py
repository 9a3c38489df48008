"""`semfleet dataset mrclam DIR -o OUT`: a UTIAS MRCLAM dataset as a scenario with a recorded run
(issue 44; ``sim.mrclam_scenario`` says what goes in and what is set aside)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from deploy.base.errors import UsageError
from deploy.base.files import write_atomically, write_text_atomically
from deploy.base.output import Console
from deploy.cli.args import class_count, seed
from deploy.cli.outputs import add_force, new_folder
from sim.generate import dump_scenario
from sim.loader import load_scenario
from sim.mrclam import MrclamError, read_mrclam
from sim.mrclam_scenario import (
    CALIBRATION_S,
    CLASSES,
    COMM_RANGE,
    RATE,
    DatasetReport,
    mrclam_scenario,
    with_digest,
)
from sim.recording import recording_bytes, sha256_of

SCENARIO = "scenario.toml"
RECORDING = "recording.npz"


def run_mrclam(args: argparse.Namespace, console: Console) -> int:
    for option, value in (
        ("--rate", args.rate),
        ("--calibrate", args.calibrate),
        ("--comm-range", args.comm_range),
    ):
        if not 0 < value < math.inf:
            raise UsageError(f"{option} {value}: must be a positive number")
    if args.seconds is not None and not 0 < args.seconds < math.inf:
        raise UsageError(f"--seconds {args.seconds}: must be a positive number of seconds")
    out = new_folder(Path(args.output), "--output", args.force)
    try:
        data = read_mrclam(args.folder)
        scenario, recording, report = mrclam_scenario(
            data,
            out / RECORDING,
            rate=args.rate,
            calibrate_s=args.calibrate,
            seconds=args.seconds,
            classes=args.classes,
            seed=args.seed,
            comm_range=args.comm_range,
            schedule_all=args.schedule_all,
        )
    except (MrclamError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    out.mkdir(parents=True, exist_ok=True)
    raw = recording_bytes(recording)
    write_atomically(out / RECORDING, lambda tmp: tmp.write_bytes(raw))
    scenario = with_digest(scenario, sha256_of(out / RECORDING))
    write_text_atomically(out / SCENARIO, _header(args, report) + dump_scenario(scenario))
    load_scenario(out / SCENARIO)  # never leave a scenario that does not load
    console.print(_summary(out, scenario.name, report))
    return 0


def _header(args: argparse.Namespace, r: DatasetReport) -> str:
    c = r.calibration
    lines = [
        f"# Written by `semfleet dataset mrclam {args.folder}` (issue 44): the recorded run is",
        f"# {RECORDING} (odometry, landmark detections, Vicon ground truth for scoring only).",
        '# Cite: K. Y. K. Leung, Y. Halpern, T. D. Barfoot, H. H. T. Liu, "The UTIAS Multi-Robot',
        '# Cooperative Localization and Mapping Dataset", IJRR 30(8):969-974, 2011.',
        f"# Steps every {1 / args.rate:g} s from t0 = {r.start:.3f} (Unix s), {r.steps} steps;",
        f"# noise calibrated against Vicon on the {c.seconds:g} s before t0 ({c.steps} steps,",
        f"# {c.sightings} landmark sightings), the variances of all residuals; robust sigmas",
        f"# (1.4826 MAD): odometry {c.odometry[0]:.4g} m, {c.odometry[1]:.4g} m, "
        f"{c.odometry[2]:.4g} rad per step, range {c.range:.4g} m, bearing {c.bearing:.4g} rad;",
        f"# plain, one step: odometry {c.odometry_std[0]:.4g}, {c.odometry_std[1]:.4g}, "
        f"{c.odometry_std[2]:.4g}; range {c.range_std:.4g}, bearing {c.bearing_std:.4g};",
        f"# odometry over {c.window:g} s windows, root mean square per step (not used): "
        + ", ".join(f"{math.sqrt(v):.4g}" for v in c.odometry_rate)
        + ";",
        f"# {100 * c.outliers:.1f} % of residuals beyond 5 robust sigmas; median range residual "
        f"{c.range_bias:.4g} m, bearing {c.bearing_bias:.4g} rad.",
        "# Set aside: robot-to-robot sightings "
        + ", ".join(f"{k} {v}" for k, v in r.robot_sightings.items())
        + "; misreads "
        + ", ".join(f"{k} {v}" for k, v in r.misreads.items())
        + "; second sightings of a landmark in one step "
        + ", ".join(f"{k} {v}" for k, v in r.duplicates.items())
        + ".",
        f"# Classes: semi-synthetic; the classifier model from seed {args.seed}, and each run "
        "draws every landmark's",
        f"# class from the prior with its own seed (class_seed = {args.seed}); a point's "
        "viewpoint is read in the world frame (heading 0).",
        "",
    ]
    return "\n".join(lines) + "\n"


def _summary(out: Path, name: str, r: DatasetReport) -> str:
    kept = sum(r.landmark_detections.values())
    aside = sum(r.robot_sightings.values()) + sum(r.misreads.values())
    c = r.calibration
    return (
        f"wrote {out / SCENARIO} and {out / RECORDING} ({name}): {r.steps} steps over "
        f"{r.seconds:g} s, {kept} landmark detections; set aside {aside} "
        f"(robot sightings {sum(r.robot_sightings.values())}, misreads "
        f"{sum(r.misreads.values())}) and {sum(r.duplicates.values())} second sightings in a "
        f"step; noise from {c.seconds:g} s before the run: range σ {c.range_std:.3g} m, "
        f"bearing σ {c.bearing_std:.3g} rad, odometry σ {c.odometry_std[0]:.3g} m, "
        f"{c.odometry_std[2]:.3g} rad per step; robot pairs within the link range at "
        f"{100 * r.link_share:.0f} % of the steps"
    )


def add_parser(sub: Any) -> None:
    p = sub.add_parser("dataset", help="turn a recorded dataset into a scenario with its run")
    dsub = p.add_subparsers(dest="dataset_command", required=True, metavar="mrclam")
    m = dsub.add_parser(
        "mrclam",
        help="a UTIAS MRCLAM dataset folder (or its .tar.xz) as OUT/scenario.toml and its "
        "recorded run, for study, launch and replay",
    )
    m.add_argument("folder", metavar="DIR", help="MRCLAM_DatasetN folder or its .tar.xz archive")
    m.add_argument("-o", "--output", required=True, metavar="OUT", help="folder to write")
    m.add_argument("--rate", type=float, default=RATE, help=f"steps per second (default {RATE:g})")
    m.add_argument(
        "--calibrate",
        type=float,
        default=CALIBRATION_S,
        metavar="SECONDS",
        help="seconds at the start used to calibrate the noise against Vicon and left out of "
        f"the run (default {CALIBRATION_S:g})",
    )
    m.add_argument(
        "--seconds", type=float, default=None, help="run only this long (default: to the end)"
    )
    m.add_argument("--classes", type=class_count, default=CLASSES, help="classes (default 3)")
    m.add_argument(
        "--seed",
        type=seed,
        default=0,
        help="seed of the classifier model and of the per-run class draws (class_seed)",
    )
    m.add_argument(
        "--comm-range",
        type=float,
        default=COMM_RANGE,
        help=f"robots exchange stacks within this true distance [m] (default {COMM_RANGE:g})",
    )
    m.add_argument(
        "--schedule-all",
        action="store_true",
        help="every pair of robots exchanges stacks at every step (a schedule), not by range",
    )
    add_force(m)
    m.set_defaults(run=run_mrclam)
