"""`semfleet study`: the paper's Monte Carlo comparison, as parallel seeded processes (or tasks of
a Dask cluster), all of its seeds or one shard of them. Parses the options, runs
:func:`deploy.study.runner.run_study`, writes its archive and plots, prints the tables.
`semfleet study merge DIR... --out DIR` combines the shards
(:func:`deploy.study.shards.merge_shards`).

Over 300 lines for a reason: one option per belief setting a study can change (each checked
against the class kind it needs, with a one-line error), and the settings written back to the
archive; splitting it would part each option from its check.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.base.build import HYPOTHESIS_MANAGEMENT
from deploy.base.errors import UsageError
from deploy.base.output import plural, runs_progress
from deploy.cli.args import (
    MAX_SEED,
    add_detector_arguments,
    detector_from_args,
    positive_int,
    seed,
)
from deploy.cli.outputs import FORCE_HELP, new_folder
from deploy.cli.scenario_args import scenario_from_args
from deploy.study.archive import study_archive, write_archive
from deploy.study.fleet import COMM_MODES, GOSSIP_MODES
from deploy.study.paper_figures import PAPER_SOURCE, PaperValue, compare, paper_world_error
from deploy.study.report import render_association, render_paper, render_summary, write_plots
from deploy.study.runner import (
    ASSOCIATE_ON,
    DEFAULT_METHODS,
    METHODS,
    RECEIVED_NEEDS,
    run_study,
    without_ids_needs,
)
from deploy.study.shards import Shard, merge_shards, shard_entry, study_key, write_merged_plots
from estimator.hybrid import (
    POSE_WINDOW,
    SLOT_EVIDENCES,
    SLOT_LINEARISATIONS,
    SPARSE_XI_ABOVE,
    XI_KINDS,
    BeliefConfig,
)
from estimator.models import GLOBAL_IDS
from estimator.sparse_xi import MAX_XI_PARENTS, XI_PARENTS
from estimator.weights import WEIGHT_ESTIMATORS


def _methods(text: str) -> list[str]:
    methods = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise argparse.ArgumentTypeError(
            f"unknown method(s) {unknown} (available: {', '.join(METHODS)})"
        )
    if "received" in methods and "distributed" not in methods:
        raise argparse.ArgumentTypeError(RECEIVED_NEEDS)
    return list(dict.fromkeys(methods))


def _shard(text: str) -> Shard:
    try:
        return Shard.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def run(args: argparse.Namespace, console: Console, own: dict[str, tuple[str, Any]]) -> int:
    """``own``: the study's options, dest → (option, default), which `study merge` refuses."""
    if args.merge is not None:
        return run_merge(args, console, own)
    if args.folders:
        raise UsageError(
            f"unexpected {args.folders[0]!r}: only `semfleet study merge DIR... --out DIR` "
            "takes folders"
        )
    if args.scenario is None:
        raise UsageError("--scenario is required (or: semfleet study merge DIR... --out DIR)")
    scenario = scenario_from_args(args)
    if args.paper and (why := paper_world_error(scenario.name)):
        raise UsageError(why)
    robot = args.snapshot_robot or scenario.robot_ids[0]
    if robot not in scenario.robot_ids:
        raise UsageError(f"--snapshot-robot: no robot {robot!r} in {scenario.name}")
    step = scenario.steps if args.snapshot_step is None else args.snapshot_step
    if not 1 <= step <= scenario.steps:
        raise UsageError(f"--snapshot-step: {step} is outside 1..{scenario.steps}")
    changes = {"weight_estimator": args.weights, "num_samples": args.samples}
    if args.max_hypotheses is not None:
        changes["max_hypotheses"] = args.max_hypotheses
    if args.robot_budget is not None:
        changes["robot_budget"] = args.robot_budget or None
    if args.semantic_poses:
        changes["semantic_poses"] = True
    if args.semantic_poses and args.hypotheses == "per_object":
        raise UsageError(
            "--semantic-poses needs a continuous belief per class realisation, and "
            "--hypotheses per_object (the default) keeps one: add --hypotheses marginal"
        )
    if args.xi == "sparse" and args.hypotheses != "per_object":
        raise UsageError(f"--xi {args.xi} needs --hypotheses per_object (one ξ per slot)")
    changes["xi"] = args.xi
    if args.xi_parents != XI_PARENTS:
        if args.hypotheses != "per_object" or args.xi == "dense":
            raise UsageError(
                "--xi-parents shapes a sparse ξ: it needs --hypotheses per_object and "
                "--xi auto or sparse"
            )
        changes["xi_parents"] = args.xi_parents
    for option, value, field in (
        ("--slot-lin", args.slot_lin, "slot_linearisation"),
        ("--slot-evidence", args.slot_evidence, "slot_evidence"),
    ):
        if value == "fused":
            continue
        if args.hypotheses != "per_object":
            raise UsageError(
                f"{option} {value} needs --hypotheses per_object "
                "(joint classes take every slot at L's point)"
            )
        changes[field] = value
    if args.window is not None:
        window = _window(args.window)
        if window is not None and args.hypotheses != "per_object":
            raise UsageError(
                f"--window {args.window} needs --hypotheses per_object "
                "(joint classes keep every pose)"
            )
        changes["window"] = window
    config = HYPOTHESIS_MANAGEMENT[args.hypotheses](**changes)
    if args.seed + args.runs - 1 > MAX_SEED:
        raise UsageError(f"--seed {args.seed} with --runs {args.runs} runs past the largest seed")
    seeds = [args.seed + i for i in range(args.runs)]
    ran = seeds if args.shard is None else args.shard.seeds(seeds)
    if not ran:
        raise UsageError(f"--shard {args.shard} of {plural(args.runs, 'run')} has no seeds")
    comm = args.comm or scenario.communication.mode
    detector = detector_from_args(args)
    if detector.ids != GLOBAL_IDS:
        if args.methods == list(DEFAULT_METHODS):
            args.methods = ["local", "distributed"]
            console.print(
                f"--ids {detector.ids}: the methods local and distributed (no centralized belief "
                "without its own association)"
            )
        elif {"centralized", "received"} & set(args.methods):
            raise UsageError(f"--ids {detector.ids}: {without_ids_needs(detector.ids)}")
        elif set(args.methods) - {"local"} and args.hypotheses != "per_object":
            raise UsageError(
                f"--ids {detector.ids}: fleet association needs --hypotheses per_object"
            )
    class_evidence = args.class_evidence == "on"
    if not class_evidence and detector.ids == GLOBAL_IDS:
        raise UsageError("--class-evidence off: only frames without global ids are associated")
    if args.associate_on != ASSOCIATE_ON[0] and detector.ids == GLOBAL_IDS:
        raise UsageError(
            f"--associate-on {args.associate_on}: only frames without global ids are associated"
        )
    out = new_folder(Path(args.out), "--out", args.force)  # before any run, not after them
    where = plural(args.jobs, "job") if args.cluster is None else f"Dask cluster {args.cluster}"
    which = f"seeds {seeds[0]}..{seeds[-1]}"
    if args.shard is not None:
        which = f"shard {args.shard}: {plural(len(ran), 'run')} of {which}"
    console.print(
        f"study: {scenario.name}, methods {', '.join(args.methods)}, "
        f"{plural(args.runs, 'run')} ({which}), "
        f"{where}, weights {args.weights}, "
        f"hypotheses {args.hypotheses}, communication {comm}"
    )
    with runs_progress(console) as progress:
        task = progress.add_task("runs", total=len(ran))
        results = run_study(
            scenario,
            args.methods,
            ran,
            config,
            args.jobs,
            step,
            lambda: progress.advance(task),
            args.comm,
            args.cluster,
            gossip=args.gossip,
            detector=detector,
            class_evidence=class_evidence,
            associate_on=args.associate_on,
        )
    settings = {
        "weight_estimator": args.weights,
        "hypotheses": args.hypotheses,
        "max_hypotheses": config.max_hypotheses,
        "robot_budget": config.robot_budget,
        "semantic_poses": config.semantic_poses,
        "classes": config.classes,
        "xi": config.xi,
        "slot_linearisation": config.slot_linearisation,
        "slot_evidence": config.slot_evidence,
        "window": config.window,
        "communication": comm,
        "gossip": args.gossip,
    }
    if config.xi_parents != XI_PARENTS:  # a default study's settings stay those of before
        settings["xi_parents"] = config.xi_parents
    if not detector.exact:  # a given-id study's settings stay those of before
        settings["detector"] = {
            "ids": detector.ids,
            "clutter": detector.clutter,
            "miss": detector.miss,
        }
        if detector.confirmable is not None:
            settings["detector"]["confirmable"] = dataclasses.asdict(detector.confirmable)
    association: dict[str, Any] = {}
    if not class_evidence:
        association["class_evidence"] = False
    if args.associate_on != ASSOCIATE_ON[0]:
        association["associate_on"] = args.associate_on
    if association:
        settings["association"] = association
    if args.shard is not None:
        key = study_key(
            scenario,
            args.methods,
            config,
            args.comm,
            args.gossip,
            detector,
            class_evidence,
            args.associate_on,
        )
        settings["shard"] = shard_entry(args.shard, seeds, step, robot, key)
    archive = study_archive(scenario.name, results, args.methods, settings)
    write_archive(out, archive)
    doc = archive.document()
    render_summary(doc, console)
    render_association(doc, console)
    paper = _against_paper(out, doc, console) if args.paper else []
    plots = write_plots(out, doc, scenario, results, step, robot, paper)
    console.print(
        f"wrote {out / 'results.json'}, {out / 'results.npz'} and {len(plots)} plots in {out}"
    )
    return 0


def _against_paper(out: Path, doc: dict[str, Any], console: Console) -> list[PaperValue]:
    """`--paper`: the table of the study's means against the paper's read-off values, the same
    rows as ``out``/paper.json; the values, for the plots."""
    rows = compare(doc)
    render_paper(rows, console)
    document = {"source": PAPER_SOURCE, "rows": [r.document() for r in rows]}
    (out / "paper.json").write_text(
        json.dumps(document, indent=1, allow_nan=False) + "\n", encoding="utf-8"
    )
    return [r.value for r in rows]


def run_merge(args: argparse.Namespace, console: Console, own: dict[str, tuple[str, Any]]) -> int:
    given = [option for dest, (option, default) in own.items() if getattr(args, dest) != default]
    if given:  # the shards decided them
        raise UsageError(f"study merge takes DIR... and --out only, not {given[0]}")
    if not args.folders:
        raise UsageError("study merge: name the shards' folders (DIR...)")
    folders = [Path(f) for f in args.folders]
    out = Path(args.out)
    if any(out.resolve() == f.resolve() for f in folders):
        raise UsageError(f"--out {out} is one of the shards: merge into another folder")
    merged = merge_shards(folders)
    new_folder(out, "--out", args.force)
    write_archive(out, merged.archive)
    doc = merged.archive.document()
    console.print(
        f"study merge: {len(folders)} shards of {doc['scenario']}, "
        f"{plural(doc['runs'], 'run')} (seeds {doc['seeds'][0]}..{doc['seeds'][-1]})"
    )
    if args.paper and (why := paper_world_error(doc["scenario"])):
        raise UsageError(why)
    render_summary(doc, console)
    paper = _against_paper(out, doc, console) if args.paper else []
    plots = write_merged_plots(out, merged, paper)
    console.print(
        f"wrote {out / 'results.json'}, {out / 'results.npz'} and {len(plots)} plots in {out}"
    )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "study",
        help="Monte Carlo comparison of methods over seeded runs; `study merge`: join shards",
        usage="%(prog)s --scenario SCENARIO [options]\n       %(prog)s merge DIR... --out DIR",
    )
    p.add_argument(
        "merge",
        nargs="?",
        choices=("merge",),
        help="combine the folders of a study's shards (--shard) into one results folder",
    )
    p.add_argument("folders", nargs="*", metavar="DIR", help="with merge: the shards' folders")
    p.add_argument("--scenario", help="scenario file or bundled name (e.g. paper); required")
    p.add_argument("--variant", action="append", default=[], metavar="NAME")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="overrides")
    p.add_argument(
        "--methods",
        type=_methods,
        default=list(DEFAULT_METHODS),
        help=f"comma-separated, from: {', '.join(METHODS)} (default: "
        f"{','.join(DEFAULT_METHODS)}; received: the centralized belief over what each robot has "
        "received, needs distributed)",
    )
    add_detector_arguments(p)
    p.add_argument(
        "--class-evidence",
        choices=("on", "off"),
        default="on",
        help="frames without ids: whether the robots' and the fleet's association weigh the "
        "class scores (default) or geometry alone (the baseline)",
    )
    p.add_argument(
        "--associate-on",
        choices=ASSOCIATE_ON,
        default=ASSOCIATE_ON[0],
        help="frames without ids: what each fleet robot's association gates on: local, its own "
        f"L, or fused, its node's D (default {ASSOCIATE_ON[0]}; the method local always uses L)",
    )
    p.add_argument("--runs", type=positive_int, default=10)
    p.add_argument("--jobs", type=positive_int, default=2, help="parallel processes")
    p.add_argument("--seed", type=seed, default=0, help="runs use seeds S, S+1, …")
    p.add_argument(
        "--shard",
        type=_shard,
        default=None,
        metavar="I/N",
        help="run only shard I of N (0 <= I < N): the seed indices i with i %% N == I; "
        "`study merge` joins the shards' folders",
    )
    p.add_argument(
        "--cluster",
        default=None,
        metavar="ADDRESS",
        help="run the seeds on the Dask cluster whose scheduler is at ADDRESS "
        "(e.g. tcp://10.0.0.5:8786; needs pip install 'semfleet[cluster]'); --jobs is ignored",
    )
    p.add_argument("--out", default="out/study", help="output folder (new or empty)")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument(
        "--paper",
        action="store_true",
        help="with the paper world: the paper's read-off values (Fig. 2b, 2d, 3a) on the plots, "
        "a table of the study's means against them, and paper.json (docs/paper.md)",
    )
    p.add_argument("--weights", choices=WEIGHT_ESTIMATORS, default="geo_conditioned")
    p.add_argument(
        "--comm",
        choices=COMM_MODES,
        default=None,
        help="communication for distributed methods: the schedule table, the range rule "
        "(scenario's range, 10 m in paper) or both (default: the scenario's mode)",
    )
    p.add_argument(
        "--gossip",
        choices=GOSSIP_MODES,
        default="delta",
        help="what the fleets' stacks carry: delta (default: the agents' lock-step protocol, "
        "the held slots some peer lacks) or full (every held slot, the fleet before issue 42); "
        'docs/architecture.md, "The study\'s gossip"',
    )
    p.add_argument("--samples", type=positive_int, default=BeliefConfig().num_samples)
    p.add_argument(
        "--hypotheses",
        choices=tuple(HYPOTHESIS_MANAGEMENT),
        default="per_object",
        help="class beliefs: per_object (default: a class belief per object, for maps of any "
        "size), or joint class realisations: marginal (pruned to a cap of 300), paper (joint "
        "ratio 1/150 and a continuous belief per realisation, to replicate the paper) or exact "
        "(no pruning, small worlds only); docs/estimator.md",
    )
    p.add_argument(
        "--xi",
        choices=XI_KINDS,
        default="auto",
        help="with --hypotheses per_object, the ξ of a slot: auto (default: dense up to "
        f"{SPARSE_XI_ABOVE} objects, sparse above), dense (the owner's exact Λ, (3n)² numbers) "
        "or sparse (a conservative Λ_s ⪯ Λ on a Bayes net's moral graph, linear in n; "
        "docs/estimator.md)",
    )
    p.add_argument(
        "--xi-parents",
        type=int,
        choices=range(MAX_XI_PARENTS + 1),
        default=XI_PARENTS,
        metavar=f"0..{MAX_XI_PARENTS}",
        help=f"a sparse ξ's Bayes net: parents of each object beyond its tree parent (default "
        f"{XI_PARENTS}); each one more buys back D's position σ for about 45 bytes per object "
        '(docs/estimator.md, "Sparse ξ")',
    )
    p.add_argument(
        "--slot-lin",
        choices=SLOT_LINEARISATIONS,
        default="fused",
        help="with --hypotheses per_object, where a robot linearises its own factors for its "
        "slot: fused (default, at its distributed belief's estimate, where its receivers are) "
        "or local (at its local belief's own point, which drifts; the reference; "
        'docs/distributed.md, "Where a slot is linearised")',
    )
    p.add_argument(
        "--slot-evidence",
        choices=SLOT_EVIDENCES,
        default="fused",
        help="with --hypotheses per_object, where a robot reads its detections' viewpoints for "
        "its slot's class evidence: fused (default, where its slot's ξ is taken) or local (at "
        "its local belief's estimate; the reference; docs/distributed.md, \"Where a slot is "
        'linearised")',
    )
    p.add_argument(
        "--window",
        metavar="STEPS|all",
        help="with --hypotheses per_object, every belief keeps the robot poses of the last "
        "STEPS to 2·STEPS steps and marginalises older ones (objects stay), so that a step and "
        f"the memory follow the map, not the mission (default {POSE_WINDOW}; all keeps every "
        'pose; docs/estimator.md, "A window of poses")',
    )
    p.add_argument(
        "--semantic-poses",
        action="store_true",
        help="semantic factors in the Gaussians: a continuous belief per class realisation, the "
        "paper's Eq. 5 taken literally (20-50x slower; implied by --hypotheses paper; "
        "docs/estimator.md)",
    )
    p.add_argument(
        "--max-hypotheses",
        type=positive_int,
        default=None,
        help=f"cap on hypotheses per belief (default {BeliefConfig().max_hypotheses}; "
        f"{BeliefConfig.exact().max_hypotheses} with --hypotheses exact)",
    )
    p.add_argument(
        "--robot-budget",
        type=int,
        default=None,
        metavar="N",
        help="hypotheses per robot whose data a belief holds (default: none; a speed knob that "
        "costs the distributed belief its calibration, docs/estimator.md; 0: none)",
    )
    p.add_argument(
        "--snapshot-step",
        type=int,
        default=None,
        help="step of the hypothesis plot (default: last)",
    )
    p.add_argument(
        "--snapshot-robot", default=None, help="robot of the hypothesis plot (default: first)"
    )
    defaults = vars(p.parse_args([]))
    own = {
        a.dest: (a.option_strings[-1], defaults[a.dest])
        for a in p._actions
        if a.option_strings and a.dest not in ("help", "out", "paper", "force")
    }
    p.set_defaults(run=lambda args, console: run(args, console, own))


def _window(text: str) -> int | None:
    """``--window``: a number of steps ≥ 1, or ``all`` (every pose kept)."""
    if text == "all":
        return None
    try:
        window = int(text)
    except ValueError:
        raise UsageError(f"--window {text!r}: a number of steps ≥ 1, or all") from None
    if window < 1:
        raise UsageError(f"--window must be ≥ 1 step (or all), got {window}")
    return window
