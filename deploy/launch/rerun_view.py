"""A launch as a Rerun recording (the optional extra ``view``): ``--view`` streams it to a
spawned viewer, ``--record FILE.rrd`` writes it to a file (docs/deploy.md, "Live view and
recordings").

The conductor already holds everything shown: the true poses of its frames, the links it
allows, and every estimate the agents publish (kept with ``LaunchPlan.keep_estimates``). After
every step :meth:`RerunLog.on_step` logs, on the timeline ``step``, each robot's truth, L and D
(``world/robots/<r>/...``: poses, 2σ ellipses, trails, objects labelled with their most probable
class), the links (``world/links``), the class probabilities and the agents' counters
(``robots/<r>/...``); docs/deploy.md has the table of entities. An estimate is logged at its own
step, whenever it arrives: a realtime run's last ones after the last step
(:meth:`RerunLog.estimates`).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rich.console import Console

from deploy.base.errors import RunFailure, UsageError
from deploy.launch.conductor import Collected, Conductor, links_at
from deploy.launch.rerun_layout import fleet_blueprint
from deploy.launch.run import LaunchOutcome, LaunchPlan, launch
from estimator.metrics import mixture_moments
from estimator.snapshot import BeliefSnapshot
from protocol.estimate import EstimateMessage
from sim.scenario import Scenario

Array = NDArray[np.float64]
Colour = tuple[int, ...]

APPLICATION = "semfleet"
INSTALL_HINT = "pip install 'semfleet[view]'"
BELIEFS = ("local", "distributed")
NSIGMA = 2.0  # as deploy/study/plots.py's ellipses
ELLIPSE_VERTICES = 48
ARROW_M = 1.0  # heading arrows, metres
RECORD_FLUSH_S = 2.0
_PALETTE = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
            (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207))  # fmt: skip
_TRUTH = (200, 200, 200)


def import_rerun() -> ModuleType:
    """The ``rerun`` module, or a usage error naming the extra that installs it."""
    try:
        import rerun
    except ImportError:
        raise UsageError(f"--view and --record need Rerun: {INSTALL_HINT}") from None
    return rerun


def has_display(environ: Mapping[str, str], platform: str = sys.platform) -> bool:
    """Whether a viewer window can open: on Linux an X11 or Wayland display must be named
    (without one the viewer exits and the SDK waits seconds for it before failing)."""
    if not platform.startswith("linux"):
        return True
    return any(environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def ellipses(mean: Array, cov: Array, nsigma: float = NSIGMA) -> Array:
    """The ``nsigma`` ellipses (m, V + 1, 2), closed, of positions mean (m, 2) with covariances
    cov (m, 2, 2)."""
    vals, vecs = np.linalg.eigh(cov)
    t = np.linspace(0.0, 2.0 * np.pi, ELLIPSE_VERTICES + 1)
    circle = np.stack([np.cos(t), np.sin(t)])  # (2, V + 1)
    scaled = vecs * (nsigma * np.sqrt(np.maximum(vals, 0.0)))[:, None, :]
    return mean[:, None, :] + np.einsum("mij,jv->mvi", scaled, circle)


def _xyz(xy: Array) -> Array:
    """(..., 2) → (..., 3) on the ground plane."""
    return np.concatenate([xy, np.zeros((*xy.shape[:-1], 1))], axis=-1)


def link_strips(
    verdict: Mapping[str, Sequence[str]], positions: Mapping[str, Array]
) -> tuple[list[Array], list[str]]:
    """One line per pair of robots with a link at this step, labelled ``a↔b`` (both hear each
    other) or ``s→r`` (only r hears s); ``verdict``: receiver → the senders it hears."""
    heard = {(s, r) for r, senders in verdict.items() for s in senders}
    strips, labels = [], []
    for a, b in sorted({tuple(sorted(p)) for p in heard}):
        both = (a, b) in heard and (b, a) in heard
        label = f"{a}↔{b}" if both else (f"{a}→{b}" if (a, b) in heard else f"{b}→{a}")
        strips.append(_xyz(np.array([positions[a][:2], positions[b][:2]])))
        labels.append(label)
    return strips, labels


class RerunLog:
    """Logs a launch's steps to one Rerun recording stream."""

    def __init__(
        self, rr: ModuleType, stream: Any, scenario: Scenario, robots: Sequence[str]
    ) -> None:
        self.rr = rr
        self.stream = stream
        self.scenario = scenario
        self.robots = list(robots)
        self.colours = {r: _PALETTE[i % len(_PALETTE)] for i, r in enumerate(scenario.robot_ids)}
        self.logged: set[tuple[str, int]] = set()
        self.trails: dict[tuple[str, str], dict[int, tuple[float, float]]] = {}

    def blueprint(self) -> Any:
        """The recording's default layout (deploy/launch/rerun_layout.py)."""
        return fleet_blueprint(self.rr.blueprint, self.scenario, self.robots)

    def world(self) -> None:
        """What does not change: axes and the objects' true positions and classes."""
        rr, s = self.rr, self.scenario
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        poses, classes = s.object_poses(), s.object_classes()
        labels = [f"o{o} class {c + 1}" for o, c in zip(s.object_ids, classes, strict=True)]
        self.stream.log(
            "world/truth/objects",
            rr.Points3D(_xyz(poses[:, :2]), labels=labels, colors=_TRUTH, radii=0.15),
            static=True,
        )

    def on_step(self, conductor: Conductor, k: int) -> None:
        """Step k's truth and links, and every estimate that arrived since the last call."""
        self.stream.set_time("step", sequence=k)
        truth = {r: conductor.frames[r][k - 1].true_pose for r in self.robots}
        for r in self.robots:
            self._pose(r, "truth", k, truth[r], None, _TRUTH)
        verdict = links_at(conductor.links, conductor.frames, self.robots, k)
        strips, labels = link_strips(verdict, truth)
        self.stream.log("world/links", self.rr.LineStrips3D(strips, labels=labels, radii=0.03))
        self.estimates(conductor.collected)

    def estimates(self, collected: Collected) -> None:
        """Every estimate not logged yet (after the run: those that came after the last step)."""
        new = [key for key in collected.estimates if key not in self.logged]
        for key in sorted(new, key=lambda rk: (rk[1], rk[0])):
            self._estimate(collected.estimates[key])
            self.logged.add(key)

    def _estimate(self, est: EstimateMessage) -> None:
        rr, log = self.rr, self.stream.log
        self.stream.set_time("step", sequence=est.k)
        for name in BELIEFS:
            snap = est.beliefs.get(name)
            if snap is None:
                continue
            pose, cov = mixture_moments(snap.weights, snap.robot_pose, snap.robot_cov)
            colour: Colour = self.colours[est.robot]
            if name == "local":  # L darker than D
                colour = tuple(int(c * 0.55) for c in colour)
            self._pose(est.robot, name, est.k, pose, cov, colour)
            self._objects(est.robot, name, snap, colour)
        for counter, value in sorted(est.counters.items()):
            log(f"robots/{est.robot}/counters/{counter}", rr.Scalars(float(value)))

    def _pose(
        self, robot: str, belief: str, k: int, pose: Array, cov: Array | None, colour: Colour
    ) -> None:
        rr, log = self.rr, self.stream.log
        path = f"world/robots/{robot}/{belief}"
        tag = {"truth": "", "local": " L", "distributed": " D"}[belief]
        x, y, theta = (float(v) for v in pose)
        shown = belief != "local"  # L's labels on hover only: they would hide D's
        point = rr.Points3D(
            [[x, y, 0.0]], labels=[f"{robot}{tag}"], colors=colour, radii=0.2, show_labels=shown
        )
        log(path, point)
        heading = [[ARROW_M * np.cos(theta), ARROW_M * np.sin(theta), 0.0]]
        log(f"{path}/heading", rr.Arrows3D(vectors=heading, origins=[[x, y, 0.0]], colors=colour))
        if cov is not None:
            ring = ellipses(np.array([[x, y]]), cov[None])[0]
            log(f"{path}/cov", rr.LineStrips3D([_xyz(ring)], colors=colour, radii=0.02))
        trail = self.trails.setdefault((robot, belief), {})
        trail[k] = (x, y)
        points = np.array([trail[j] for j in sorted(trail) if j <= k])
        log(f"{path}/trail", rr.LineStrips3D([_xyz(points)], colors=colour, radii=0.02))

    def _objects(self, robot: str, belief: str, snap: BeliefSnapshot, colour: Colour) -> None:
        rr, log = self.rr, self.stream.log
        path = f"world/robots/{robot}/{belief}/objects"
        pose, cov = mixture_moments(snap.weights, snap.object_pose, snap.object_cov)
        prob = snap.marginals(self.scenario.num_classes)
        best = np.argmax(prob, axis=1) if len(prob) else np.zeros(0, dtype=int)
        labels = [
            f"o{o} class {c + 1} ({prob[i, c]:.2f})"
            for i, (o, c) in enumerate(zip(snap.object_ids, best, strict=True))
        ]
        xy = pose[:, :2].reshape(-1, 2)
        shown = belief != "local"
        log(
            path,
            rr.Points3D(_xyz(xy), labels=labels, colors=colour, radii=0.12, show_labels=shown),
        )
        rings = ellipses(xy, cov.reshape(-1, 2, 2)) if len(xy) else np.zeros((0, 2, 2))
        log(f"{path}/cov", rr.LineStrips3D([_xyz(r) for r in rings], colors=colour, radii=0.015))
        log(
            f"robots/{robot}/{belief}/classes",
            rr.Tensor(prob, dim_names=["object", "class"]),
            rr.AnyValues(object_ids=list(snap.object_ids)),
        )

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()


def _viewer_on_path() -> None:
    """``rerun`` is the viewer the ``view`` extra installs next to this Python; the SDK looks
    for it on PATH, which a venv's ``semfleet`` run without activating the venv lacks."""
    here = Path(sys.executable).parent
    if shutil.which("rerun") is None and (here / "rerun").exists():
        os.environ["PATH"] = f"{here}{os.pathsep}{os.environ.get('PATH', '')}"


def add_options(p: argparse.ArgumentParser) -> None:
    """``--view`` and ``--record FILE.rrd``, of ``demo``, ``launch`` and ``chaos``."""
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--view",
        action="store_true",
        help=f"show the run live in the Rerun viewer (needs a display and {INSTALL_HINT})",
    )
    g.add_argument(
        "--record",
        type=Path,
        metavar="FILE.rrd",
        help="record the run for the Rerun viewer instead (`rerun FILE.rrd` opens it)",
    )


def check_view(view: bool, record: Path | None) -> ModuleType | None:
    """``rerun`` for ``--view`` or ``--record`` (None for neither); a :class:`UsageError`
    without a display for ``--view`` or without Rerun. Commands call it before they start."""
    if view and not has_display(os.environ):
        raise UsageError(
            "--view: no display here (DISPLAY and WAYLAND_DISPLAY are unset); record with "
            "--record FILE.rrd and open it with `rerun FILE.rrd` where there is one"
        )
    return import_rerun() if view or record is not None else None


def launch_recorded(
    plan: LaunchPlan, console: Console, args: argparse.Namespace, name: str
) -> LaunchOutcome:
    """:func:`~deploy.launch.run.launch` with the live table, recorded as the command's
    ``--view``/``--record`` ask (the plan must keep its estimates)."""
    log = open_log(args.view, args.record, name, plan.scenario, plan.robots)
    if log is None:
        return launch(plan, console)
    try:
        outcome = launch(plan, console, log.on_step)
        log.estimates(outcome.collected)
    finally:
        log.close()  # what was recorded of a run that failed too
    if args.record is not None:
        console.print(f"recorded the run in {args.record} (open it with: rerun {args.record})")
    return outcome


def open_log(
    view: bool, record: Path | None, name: str, scenario: Scenario, robots: Sequence[str]
) -> RerunLog | None:
    """A recording for ``--view`` (a spawned viewer) or ``--record FILE``; None for neither.
    Raises :class:`UsageError` without Rerun, without a display for ``--view`` or when FILE
    cannot be written, :class:`RunFailure` when the viewer does not start."""
    rr = check_view(view, record)
    if rr is None:
        return None
    # A file has no one waiting: fewer, larger chunks (measured: 3 steps of 2 robots 396 kB,
    # 622 kB with the default 0.2 s).
    batching = rr.ChunkBatcherConfig(flush_tick=RECORD_FLUSH_S) if record else None
    stream = rr.RecordingStream(APPLICATION, batcher_config=batching)
    log = RerunLog(rr, stream, scenario, robots)
    if record is not None:
        try:
            record.parent.mkdir(parents=True, exist_ok=True)
            record.open("ab").close()
            stream.save(record, default_blueprint=log.blueprint())
        except OSError as exc:
            raise UsageError(f"--record {record}: cannot write there ({exc.strerror})") from None
    else:
        _viewer_on_path()
        try:
            stream.spawn(default_blueprint=log.blueprint())
        except RuntimeError as exc:
            first = str(exc).strip().splitlines()[0]
            raise RunFailure(f"--view: the Rerun viewer did not start: {first}") from None
    stream.send_recording_name(name)
    log.world()
    return log
