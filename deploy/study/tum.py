"""Trajectories of a hybrid-belief results folder as TUM files (docs/results.md, "TUM
trajectories"), for evo (``evo_ape``, ``evo_traj``) and other trajectory tools.

A TUM file has one pose per line, ``timestamp tx ty tz qx qy qz qw``. Our poses are SE(2): z = 0
and the rotation is the yaw θ about z, q = (0, 0, sin θ/2, cos θ/2). The timestamp of step k is
k × ``period``. A step without an estimate (a launch whose agent missed it) has no line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from deploy.base.errors import UsageError
from deploy.study.archive import read_folder

Array = NDArray[np.float64]

TRUTH = "truth"
# Enough digits to give back every float64 pose exactly.
_FORMAT = "%.6f %.17g %.17g 0 0 0 %.17g %.17g"


@dataclass(frozen=True, slots=True)
class TumFile:
    """One written trajectory: ``seed``, ``robot``, ``source`` (a method, or :data:`TRUTH`),
    ``poses`` (how many lines) and ``rmse_m``: the root mean square of the position error
    against the truth at the same steps (NaN for the truth itself), what ``evo_ape`` reports
    for the translation without alignment."""

    path: Path
    seed: int
    robot: str
    source: str
    poses: int
    rmse_m: float


def tum_lines(poses: Array, period: float) -> list[str]:
    """TUM lines of the finite rows of ``poses`` (steps, 3) x, y, θ; row k−1 is step k."""
    steps = np.arange(1, len(poses) + 1)
    known = np.all(np.isfinite(poses), axis=1)
    x, y, theta = poses[known].T
    rows = np.column_stack([steps[known] * period, x, y, np.sin(theta / 2), np.cos(theta / 2)])
    return [_FORMAT % tuple(row) for row in rows]


def export_tum(results: Path, out: Path, period: float = 1.0) -> list[TumFile]:
    """Every run's trajectories of the results folder ``results`` into
    ``out/seed-S/ROBOT_SOURCE.tum``: the truth and the estimate of every method that recorded
    one (``local`` is L, ``distributed`` D)."""
    doc, arrays = read_folder(results)
    if doc["study"] != "hybrid":
        raise UsageError(
            f"{results}: a {doc['study']} study; TUM export reads hybrid-belief results"
        )
    methods = [m for m in doc["methods"] if f"{m}/robot_pose" in arrays]
    if "true_robot_pose" not in arrays or not methods:
        raise UsageError(
            f"{results}/results.npz holds no trajectories: it was written before runs recorded "
            "them (issue 15); run the study or launch again"
        )
    truth = arrays["true_robot_pose"]
    written = []
    for i, seed in enumerate(doc["seeds"]):
        folder = out / f"seed-{seed}"
        folder.mkdir(parents=True, exist_ok=True)
        for j, robot in enumerate(doc["robots"]):
            tracks = {TRUTH: truth[i, j], **{m: arrays[f"{m}/robot_pose"][i, j] for m in methods}}
            for source, poses in tracks.items():
                path = folder / f"{robot}_{source}.tum"
                lines = tum_lines(poses, period)
                path.write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")
                rmse = np.nan if source == TRUTH else _rmse(poses, truth[i, j])
                written.append(TumFile(path, int(seed), robot, source, len(lines), rmse))
    return written


def _rmse(poses: Array, truth: Array) -> float:
    """Position RMSE over the steps both have."""
    both = np.all(np.isfinite(poses), axis=1) & np.all(np.isfinite(truth), axis=1)
    if not both.any():
        return float("nan")
    error = np.linalg.norm(poses[both, :2] - truth[both, :2], axis=1)
    return float(np.sqrt(np.mean(error**2)))
