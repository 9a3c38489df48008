"""Odometry and camera measurements of a world, with common random numbers.

Every draw is a pure function of (seed, stream, step, landmark id), as in ``sim.sensors``: each
method of a Monte Carlo run, and each run order, sees the very same measurements for one seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator.models.se2 import wrap_angle
from sim.ufastslam.world import UWorld

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

_ODOMETRY, _CAMERA = 1, 2
_MAX_SEED = 2**63 - 1
# A noisy range never reaches zero: the filter rejects r below its minimum anyway.
_MIN_RANGE = 1e-3


@dataclass(frozen=True, slots=True)
class Frame:
    """The measurements of step k: landmark ``ids`` (n,) and their (r, b) ``z`` (n, 2)."""

    k: int
    ids: IntArray
    z: Array


@dataclass(frozen=True, slots=True)
class Run:
    """One seeded run: true poses (steps + 1, 3), measured odometry (steps, 2) and the frames of
    k = 1..steps."""

    seed: int
    truth: Array
    odometry: Array
    frames: tuple[Frame, ...]


def _normals(seed: int, stream: int, k: int, landmark: int, size: int) -> Array:
    seq = np.random.SeedSequence([seed, stream, k, landmark])
    return np.random.default_rng(seq).standard_normal(size)


def simulate(world: UWorld, seed: int) -> Run:
    """Measurements of one run; seeds are integers in [0, 2⁶³)."""
    if (
        isinstance(seed, bool)
        or not isinstance(seed, int | np.integer)
        or not 0 <= seed <= _MAX_SEED
    ):
        raise ValueError(f"seed must be an integer in [0, 2**63), got {seed!r}")
    seed = int(seed)
    o, cam = world.odometry, world.camera
    odometry = np.empty((world.steps, 2))
    frames = []
    ids = np.asarray(world.landmark_ids, dtype=np.int64)
    for k in range(1, world.steps + 1):
        v, w = world.controls[k - 1]
        e = _normals(seed, _ODOMETRY, k, 0, 2)
        odometry[k - 1] = (
            (1.0 + o.scale_error) * v + o.speed_std * e[0],
            w + o.yaw_rate_bias + o.yaw_rate_std * e[1],
        )
        seen, z_true = world.visible(k)
        z = np.empty_like(z_true)
        for i, j in enumerate(seen):
            n = _normals(seed, _CAMERA, k, int(ids[j]), 2)
            z[i, 0] = max(_MIN_RANGE, z_true[i, 0] + cam.range_std * n[0])
            z[i, 1] = wrap_angle(z_true[i, 1] + cam.bearing_std * n[1])
        frames.append(Frame(k, ids[seen], z))
    return Run(seed, world.trajectory.copy(), odometry, tuple(frames))
