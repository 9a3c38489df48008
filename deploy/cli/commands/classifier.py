"""`semfleet classifier sample | fit`: draw score samples from a scenario's classifier model, and
learn a viewpoint-dependent model from samples (docs/models.md, "Learned classifier models")."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from deploy.base.errors import UsageError
from deploy.base.files import write_atomically
from deploy.cli.args import positive_int, seed
from deploy.cli.outputs import add_force, figure_file, new_file
from deploy.cli.scenario_args import add_scenario_arguments, scenario_from_args
from deploy.study.classifier_fit import Fit, fit_classifier, truth_gap
from deploy.study.classifier_samples import MAX_SAMPLES, draw_samples, read_samples, write_samples
from estimator.models import LearnedClassifier
from estimator.models.classifier import OBJECT_TO_CAMERA, VIEWPOINTS, view_offset
from sim.learned_file import save_learned
from sim.loader import load_scenario


def run_sample(args: argparse.Namespace, console: Console) -> int:
    scenario = scenario_from_args(args)
    if args.n > MAX_SAMPLES:
        raise UsageError(f"-n {args.n}: at most {MAX_SAMPLES} samples")
    out = new_file(Path(args.output), "--output", args.force)
    model = scenario.classifier.build()
    samples = draw_samples(model, args.n, np.random.default_rng(args.seed), args.viewpoint)
    write_atomically(out, lambda tmp: write_samples(samples, tmp))
    console.print(
        f"wrote {out}: {args.n} samples of the {scenario.classifier.model} model of "
        f"{scenario.name} (M = {model.num_classes}, seed {args.seed}, ψ {args.viewpoint})",
        markup=False,
        highlight=False,
    )
    return 0


def run_fit(args: argparse.Namespace, console: Console) -> int:
    samples_path = Path(args.samples)
    out = new_file(Path(args.output), "--output", args.force)
    plot_text = args.plot or str(out.with_suffix(".png"))
    plot, note = figure_file(plot_text, "--plot", args.force, out.stem)
    if plot.resolve() == out.resolve():
        raise UsageError(f"--plot {plot}: the model file (--output) itself; name another figure")
    samples = read_samples(samples_path)
    truth = None
    if args.truth is not None:
        truth = load_scenario(args.truth).classifier.build()
        if truth.num_classes != samples.num_classes:
            raise UsageError(
                f"--truth {args.truth}: {truth.num_classes} classes, the samples have "
                f"{samples.num_classes}"
            )
    fit = fit_classifier(samples, args.seed)
    # The file records the samples' convention, so that the estimator, which always passes
    # semfleet's ψ (object → camera), evaluates the model where it was learned. The --truth
    # table and the plot compare in semfleet's ψ too: the saved model, the truth scenario's
    # model, and the samples turned back by the convention's offset.
    model = replace(fit.model, viewpoint=args.viewpoint)
    write_atomically(out, lambda tmp: save_learned(model, tmp))
    for table in _quality_tables(fit):
        console.print(table)
    if truth is not None:
        console.print(_truth_table(model, truth))
    from deploy.study.classifier_plot import save_fit_plot

    ours = replace(samples, psi=_wrap(samples.psi - view_offset(args.viewpoint)))
    write_atomically(plot, lambda tmp: save_fit_plot(tmp, ours, model, truth))
    console.print(
        f"wrote {out} ({len(samples.psi)} samples, M = {samples.num_classes}, "
        f"{fit.model.means[0].inducing.size} inducing viewpoints) and {plot}"
        + (f" ({note})" if note else ""),
        markup=False,
        highlight=False,
    )
    return 0


def _quality_tables(fit: Fit) -> tuple[Table, Table]:
    """Per score component the GP's hyperparameters and leave-one-out (LOO) RMSE; per class the
    covariance scale's range over ψ, the mean LOO log-likelihood and the share of LOO residuals
    inside the model's 95 % ellipse (a calibrated model: about 95 %)."""
    scores = Table(title="fit quality per score: GP length scale (rad), signal and noise std")
    for name in ("class", "n", "score", "ℓ", "signal std", "noise std", "LOO RMSE"):
        scores.add_column(name, justify="right", no_wrap=True)
    classes = Table(title="fit quality per class (LOO: each sample predicted without itself)")
    for name in ("class", "Σ scale over ψ", "LOO log-lik", "in 95 % ellipse"):
        classes.add_column(name, justify="right", no_wrap=True)
    for c, cf in enumerate(fit.classes):
        for i, comp in enumerate(cf.components):
            scores.add_row(
                str(c + 1) if i == 0 else "",
                str(cf.count) if i == 0 else "",
                f"z{i + 1}",
                f"{comp.length_scale:.3g}",
                f"{comp.amplitude:.3g}",
                f"{comp.noise_std:.3g}",
                f"{comp.loo_rmse:.3g}",
            )
        lo, hi = cf.scale_range
        classes.add_row(
            str(c + 1),
            f"{lo:.3g}–{hi:.3g}",
            f"{cf.loo_log_likelihood:.3f}",
            f"{100 * cf.coverage95:.1f} %",
        )
    return scores, classes


def _wrap(psi: np.ndarray) -> np.ndarray:
    return np.asarray(np.mod(psi + np.pi, 2.0 * np.pi) - np.pi)


def _truth_table(model: LearnedClassifier, truth: Any) -> Table:
    t = Table(title="against the model that drew the samples (--truth), over 360 viewpoints")
    for name in ("class", "max |h − h_true|", "mean KL(true ‖ fit)", "max KL"):
        t.add_column(name, justify="right", no_wrap=True)
    for c, gap in enumerate(truth_gap(model, truth)):
        t.add_row(
            str(c + 1), f"{gap.max_mean_error:.3f}", f"{gap.mean_kl:.4f}", f"{gap.max_kl:.4f}"
        )
    return t


def add_parser(sub: Any) -> None:
    p = sub.add_parser("classifier", help="sample a classifier model; learn one from samples")
    csub = p.add_subparsers(dest="classifier_command", required=True, metavar="sample|fit")
    sample = csub.add_parser("sample", help="draw (class, ψ, scores) samples of a scenario's model")
    add_scenario_arguments(sample)
    sample.add_argument("-n", type=positive_int, required=True, help="number of samples")
    sample.add_argument("-o", "--output", required=True, help="CSV file to write")
    sample.add_argument("--seed", type=seed, default=0)
    add_force(sample)
    sample.add_argument(*_VIEWPOINT[0], **_VIEWPOINT[1], help="the convention of ψ to write")
    sample.set_defaults(run=run_sample)
    fit = csub.add_parser("fit", help="learn h_c(ψ), Σ_c(ψ) from samples by GP regression")
    fit.add_argument("samples", help="CSV file of samples (class,psi,z1,…,zM)")
    fit.add_argument("-o", "--output", required=True, help="model file (.npz) to write")
    fit.add_argument(
        "--plot",
        default=None,
        help="the figure to write: .png, .pdf or .svg (default: the model's name with .png)",
    )
    fit.add_argument(
        "--truth",
        default=None,
        metavar="SCENARIO",
        help="compare with this scenario's classifier model (the one that drew the samples)",
    )
    fit.add_argument("--seed", type=seed, default=0, help="the optimiser's restarts and subsets")
    add_force(fit)
    fit.add_argument(
        *_VIEWPOINT[0],
        **_VIEWPOINT[1],
        help="the convention of the samples' ψ, recorded in the model file",
    )
    fit.set_defaults(run=run_fit)


# object_to_camera: the azimuth of the camera seen from the object (semfleet's ψ);
# camera_to_object: the direction from the camera to the object (ψ + π), the paper's wording
_VIEWPOINT: tuple[tuple[str, ...], dict[str, Any]] = (
    ("--viewpoint",),
    {"choices": VIEWPOINTS, "default": OBJECT_TO_CAMERA},
)
