"""A recorded run (issue 44): what real robots measured, step by step, in place of the simulated
sensors — odometry and point-landmark detections (bearing, range) — with the ground truth kept
for scoring and for the link models only (``SensorFrame.true_pose``; an estimator never reads it).

A scenario names its recording in ``[recording]`` (``file``, relative to the scenario's folder,
and its ``sha256``); :class:`sim.sensors.Simulator` then takes each frame's odometry and
detections from the file and draws only the class scores, seeded per run, from the classifier
model at the true viewpoint (the semi-synthetic part: no public multi-robot dataset comes with
viewpoint-dependent class scores).

The file is a NumPy ``.npz`` archive of plain arrays (no pickles), R robots, K steps, N
detections:

- ``robots`` (R,) str: robot ids, in the scenario's order;
- ``times`` (K + 1,): t₀ … t_K, the end of each step (seconds; provenance only);
- ``truth`` (R, K + 1, 3): the true poses x₀ … x_K (x, y, θ);
- ``odometry`` (R, K, 3): step k's measured motion x_{k−1}⁻¹ ∘ x_k, row k − 1;
- ``det_robot`` (N,), ``det_step`` (N,), ``det_object`` (N,): who saw which object at which
  step (1 … K), sorted by robot, step and object, at most one detection of an object a step;
- ``det_z`` (N, 2): each detection's (bearing, range), the bearing in the robot's body frame.
"""

from __future__ import annotations

import hashlib
import io
import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

ARRAYS = ("robots", "times", "truth", "odometry", "det_robot", "det_step", "det_object", "det_z")


class RecordingError(ValueError):
    """A recording that cannot be used; the message names the file and the array."""


@dataclass(frozen=True, eq=False)
class Recording:
    """A recorded run as arrays (module docstring)."""

    robots: tuple[str, ...]
    times: Array
    truth: Array
    odometry: Array
    det_robot: IntArray
    det_step: IntArray
    det_object: IntArray
    det_z: Array
    _index: dict[tuple[int, int], tuple[int, int]] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        check(self)
        starts = np.flatnonzero(
            np.r_[True, (np.diff(self.det_robot) != 0) | (np.diff(self.det_step) != 0)]
        )
        ends = np.r_[starts[1:], len(self.det_robot)]
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            self._index[(int(self.det_robot[a]), int(self.det_step[a]))] = (a, b)

    @property
    def steps(self) -> int:
        return int(self.odometry.shape[1])

    def detections(self, robot: int, k: int) -> tuple[IntArray, Array]:
        """Object ids (D,) and (bearing, range) (D, 2) of robot index ``robot`` at step ``k``."""
        a, b = self._index.get((robot, k), (0, 0))
        return self.det_object[a:b], self.det_z[a:b]


def check(rec: Recording) -> None:
    """Raise RecordingError (naming the array) unless the arrays fit each other."""
    r, k1 = len(rec.robots), len(rec.times)
    k = k1 - 1
    n = len(rec.det_robot)
    shapes = {
        "times": (rec.times.shape, (k1,)),
        "truth": (rec.truth.shape, (r, k1, 3)),
        "odometry": (rec.odometry.shape, (r, k, 3)),
        "det_step": (rec.det_step.shape, (n,)),
        "det_object": (rec.det_object.shape, (n,)),
        "det_z": (rec.det_z.shape, (n, 2)),
    }
    for name, (got, want) in shapes.items():
        if got != want:
            raise RecordingError(f"{name}: shape {got}, expected {want}")
    if r < 1 or k < 1:
        raise RecordingError("robots: a recording needs at least one robot and one step")
    for name, a in (("times", rec.times), ("truth", rec.truth), ("odometry", rec.odometry)):
        if not np.isfinite(a).all():
            raise RecordingError(f"{name}: non-finite number")
    if not np.isfinite(rec.det_z).all() or (n and not (rec.det_z[:, 1] > 0).all()):
        raise RecordingError("det_z: a bearing or range that is not finite, or a range ≤ 0")
    if n and not (np.abs(rec.det_z[:, 0]) <= math.pi + 1e-9).all():
        raise RecordingError("det_z: a bearing outside ±π")
    if n and not ((rec.det_robot >= 0) & (rec.det_robot < r)).all():
        raise RecordingError(f"det_robot: an index outside 0 … {r - 1}")
    if n and not ((rec.det_step >= 1) & (rec.det_step <= k)).all():
        raise RecordingError(f"det_step: a step outside 1 … {k}")
    key = np.stack([rec.det_robot, rec.det_step, rec.det_object], axis=1)
    if n > 1:
        later = np.lexsort(key.T[::-1])
        if not (later == np.arange(n)).all():
            raise RecordingError("det_robot: detections not sorted by robot, step and object")
        same = (np.diff(key, axis=0) == 0).all(axis=1)
        if same.any():
            i = int(np.argmax(same))
            raise RecordingError(
                f"det_object: object {key[i, 2]} twice at step {key[i, 1]} of robot "
                f"{rec.robots[key[i, 0]]} (one detection of an object a step)"
            )


def recording_bytes(rec: Recording) -> bytes:
    """The ``.npz`` bytes of ``rec`` (uncompressed, no pickles; the same bytes for the same
    arrays)."""
    buffer = io.BytesIO()
    np.savez(
        buffer,
        robots=np.array(rec.robots, dtype=str),
        times=rec.times,
        truth=rec.truth,
        odometry=rec.odometry,
        det_robot=rec.det_robot,
        det_step=rec.det_step,
        det_object=rec.det_object,
        det_z=rec.det_z,
    )
    return buffer.getvalue()


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_recording(path: str | Path, sha256: str | None = None) -> Recording:
    """The recording in ``path``; RecordingError naming the file (and array) if it cannot be
    read, does not have ``sha256`` (when given), or its arrays do not fit each other."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if sha256 is not None and hashlib.sha256(raw).hexdigest() != sha256:
        raise RecordingError(f"{p}: its sha256 is not the one the scenario states")
    return _parse(p, raw)


_CACHE: dict[tuple[str, str], Recording] = {}


def cached_recording(path: str, sha256: str) -> Recording:
    """:func:`read_recording`, the arrays kept for the last few files (every run of a study
    reads the same one); the file's bytes are read and hashed at every call, so a changed
    file is never taken for the one the scenario names."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if hashlib.sha256(raw).hexdigest() != sha256:
        raise RecordingError(f"{p}: its sha256 is not the one the scenario states")
    key = (str(p), sha256)
    held = _CACHE.get(key)
    if held is None:
        held = _parse(p, raw)
        if len(_CACHE) >= 4:
            _CACHE.clear()
        _CACHE[key] = held
    return held


def _parse(p: Path, raw: bytes) -> Recording:
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            missing = [a for a in ARRAYS if a not in z.files]
            if missing:
                raise RecordingError(f"{p}: missing arrays {', '.join(missing)}")
            arrays = {a: z[a] for a in ARRAYS}
    except RecordingError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise RecordingError(f"{p}: not a recording (.npz) ({exc})") from None
    try:
        return Recording(
            tuple(str(r) for r in arrays["robots"].tolist()),
            np.asarray(arrays["times"], dtype=float),
            np.asarray(arrays["truth"], dtype=float),
            np.asarray(arrays["odometry"], dtype=float),
            _ints(arrays["det_robot"]),
            _ints(arrays["det_step"]),
            _ints(arrays["det_object"]),
            np.asarray(arrays["det_z"], dtype=float).reshape(-1, 2),
        )
    except RecordingError as exc:
        raise RecordingError(f"{p}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{p}: arrays of the wrong type ({exc})") from None


def _ints(a: NDArray[np.generic]) -> IntArray:
    if a.dtype.kind not in "iu":
        raise RecordingError(f"expected integers, got {a.dtype}")
    return np.asarray(a, dtype=np.int64).reshape(-1)


def fits(rec: Recording, robots: Sequence[str], steps: int, objects: Sequence[int]) -> str | None:
    """Why ``rec`` does not fit a scenario of these robots, steps and object ids, or None."""
    if tuple(robots) != rec.robots:
        return f"robots {list(rec.robots)}, the scenario's are {list(robots)}"
    if rec.steps != steps:
        return f"{rec.steps} steps, the scenario has {steps}"
    unknown = sorted(set(rec.det_object.tolist()) - set(objects))
    if unknown:
        return f"detections of objects {unknown[:5]} that the scenario does not list"
    return None
