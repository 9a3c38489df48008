"""Reading a UTIAS MRCLAM dataset (Leung, Halpern, Barfoot & Liu, IJRR 30(8):969–974, 2011):
the files of one ``MRCLAM_DatasetN`` folder, or of its ``.tar.xz`` archive as shipped, checked
row by row (issue 44, item 2; the format is in ``../shared/data/mrclam/README.md``).

Five robots drive for about 900 s among 15 point landmarks. Per robot: Vicon ground truth
(time, x, y, θ), wheel odometry as a stream of velocity commands (time, v, ω) and camera
measurements of barcodes (time, barcode, range, bearing). ``Barcodes.dat`` maps subjects to
barcodes: subjects 1–5 are the robots, 6–20 the landmarks; a measured barcode of a robot is a
sighting of that robot, one in no row a misread.

What this module gives, and nothing else: the tables as read (:class:`MrclamDataset`), the
robot's motion between two times integrated from its velocity commands (:class:`Odometry`: each
command held until the next, integrated exactly along its arc), and each measurement sorted
into a landmark sighting, a robot sighting or a misread (:func:`sightings`). Ground truth is
kept for scoring only; whatever turns the tables into a run never hands it to an estimator.
:func:`calibrate` measures the noise against Vicon on a stretch of data that a run should then
not be scored on.

Over 300 lines for a reason: the reader, the odometry and the calibration read the same tables
of one format, and every check of a table names the file and row it read; apart, the format's
rules would be split from the code that relies on them.
"""

from __future__ import annotations

import io
import lzma
import math
import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

ROBOTS = 5
LANDMARK_SUBJECTS = range(6, 21)
SMALL_OMEGA = 1e-9  # rad/s: below this a command is a straight line
# file → (columns, what they are)
_COLUMNS = {
    "Barcodes.dat": 2,
    "Landmark_Groundtruth.dat": 5,
    "Groundtruth": 4,
    "Odometry": 3,
    "Measurement": 4,
}


class MrclamError(ValueError):
    """A folder or archive that is not a readable MRCLAM dataset; the message names the file
    and, where there is one, the row (1-based line number in the file)."""


@dataclass(frozen=True, slots=True)
class RobotLog:
    """One robot's files: ``groundtruth`` (N, 4) time, x, y, θ; ``odometry`` (N, 3) time, v,
    ω; ``measurements`` (N, 4) time, barcode, range, bearing. Times in Unix seconds."""

    subject: int
    groundtruth: Array
    odometry: Array
    measurements: Array


@dataclass(frozen=True, slots=True)
class MrclamDataset:
    """``barcodes``: barcode → subject; ``landmarks``: subject → Vicon (x, y); ``robots``: the
    five robots' logs, subjects 1–5 in order."""

    name: str
    barcodes: dict[int, int]
    landmarks: dict[int, tuple[float, float]]
    robots: tuple[RobotLog, ...]

    def robot_barcodes(self) -> dict[int, int]:
        """barcode → robot subject (1–5)."""
        return {b: s for b, s in self.barcodes.items() if 1 <= s <= ROBOTS}


def read_mrclam(path: str | Path) -> MrclamDataset:
    """The dataset in folder ``path`` (its files directly inside) or in the ``.tar.xz`` archive
    ``path`` (one folder inside, as shipped). Raises :class:`MrclamError`."""
    path = Path(path)
    if path.is_dir():
        texts = _folder(path)
        name = path.name
    elif path.is_file() and path.name.endswith((".tar.xz", ".txz")):
        texts = _archive(path)
        name = path.name.removesuffix(".tar.xz").removesuffix(".txz")
    elif path.exists():
        raise MrclamError(f"{path}: not a folder nor a .tar.xz archive of an MRCLAM dataset")
    else:
        raise MrclamError(f"{path}: no such folder or archive")
    lines, rows = _table(texts, "Barcodes.dat", 2)
    barcodes: dict[int, int] = {}
    subjects: set[int] = set()
    for line, (subject, barcode) in zip(lines, rows.tolist(), strict=True):
        s, b = _whole(subject, "Barcodes.dat", line), _whole(barcode, "Barcodes.dat", line)
        if b in barcodes or s in subjects:
            raise MrclamError(f"Barcodes.dat: row {line}: subject {s} or barcode {b} repeated")
        barcodes[b] = s
        subjects.add(s)
    missing = [s for s in (*range(1, ROBOTS + 1), *LANDMARK_SUBJECTS) if s not in subjects]
    if missing:
        raise MrclamError(f"Barcodes.dat: no barcode for subjects {missing}")
    landmarks = {}
    lines, rows = _table(texts, "Landmark_Groundtruth.dat", 5)
    for line, row in zip(lines, rows.tolist(), strict=True):
        s = _whole(row[0], "Landmark_Groundtruth.dat", line)
        if s not in LANDMARK_SUBJECTS or s in landmarks:
            raise MrclamError(
                f"Landmark_Groundtruth.dat: row {line}: subject {s} is not a landmark (6–20) "
                "or is repeated"
            )
        landmarks[s] = (float(row[1]), float(row[2]))
    robots = []
    for r in range(1, ROBOTS + 1):
        logs = []
        for kind in ("Groundtruth", "Odometry", "Measurement"):
            name_r = f"Robot{r}_{kind}.dat"
            lines, data = _table(texts, name_r, _COLUMNS[kind])
            _increasing(data[:, 0], name_r, lines)
            logs.append(data)
        robots.append(RobotLog(r, *logs))
    for log in robots:
        if not len(log.odometry) or not len(log.groundtruth):
            raise MrclamError(f"Robot{log.subject}: no odometry or no ground truth rows")
    return MrclamDataset(name, barcodes, landmarks, tuple(robots))


def _folder(path: Path) -> dict[str, str]:
    out = {}
    for f in sorted(path.iterdir()):
        if f.is_file() and f.suffix == ".dat":
            try:
                out[f.name] = f.read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as exc:
                raise MrclamError(f"{f.name}: cannot be read ({exc})") from None
    return out


def _archive(path: Path) -> dict[str, str]:
    out = {}
    try:
        with tarfile.open(path, "r:xz") as tar:
            for member in tar.getmembers():
                if not member.isfile() or not member.name.endswith(".dat"):
                    continue
                handle = tar.extractfile(member)
                if handle is None:
                    continue
                out[Path(member.name).name] = io.TextIOWrapper(handle, encoding="utf-8").read()
    except (tarfile.TarError, lzma.LZMAError, OSError, EOFError, UnicodeDecodeError) as exc:
        raise MrclamError(f"{path.name}: not a readable .tar.xz archive ({exc})") from None
    return out


def _table(texts: dict[str, str], name: str, columns: int) -> tuple[list[int], Array]:
    """(line numbers, numbers (N, columns)) of file ``name``'s data rows; ``#`` lines and blank
    lines are skipped. Parsed at once, row by row only to name a broken row."""
    if name not in texts:
        raise MrclamError(
            f"{name}: missing (an MRCLAM folder holds Barcodes.dat, Landmark_Groundtruth.dat "
            "and Robot1–5 Groundtruth, Odometry and Measurement .dat files)"
        )
    lines, fields = [], []
    for line, text in enumerate(texts[name].splitlines(), start=1):
        row = text.split()
        if row and not row[0].startswith("#"):
            lines.append(line)
            fields.append(row)
    for line, row in zip(lines, fields, strict=True):
        if len(row) != columns:
            raise MrclamError(f"{name}: row {line}: expected {columns} numbers, got {len(row)}")
    try:
        data = np.array(fields, dtype=float).reshape(-1, columns)
    except ValueError:
        for line, row in zip(lines, fields, strict=True):
            try:
                [float(f) for f in row]
            except ValueError:
                raise MrclamError(
                    f"{name}: row {line}: not a number in {' '.join(row)!r}"
                ) from None
        raise
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if len(bad):
        raise MrclamError(f"{name}: row {lines[int(bad[0])]}: a number that is not finite")
    return lines, data


def _whole(value: float, name: str, line: int) -> int:
    if value != int(value) or value < 0:
        raise MrclamError(f"{name}: row {line}: {value:g} is not a subject or barcode number")
    return int(value)


def _increasing(times: Array, name: str, lines: list[int]) -> None:
    back = np.flatnonzero(np.diff(times) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise MrclamError(f"{name}: row {lines[i]}: time {times[i]:.3f} before the row above")


class Odometry:
    """A robot's dead-reckoned pose at any time, from its velocity commands: each command
    (v, ω) holds from its time to the next command's, integrated exactly (an arc of radius
    v/ω); before the first command the robot stands still, after the last it keeps it."""

    def __init__(self, commands: Array) -> None:
        t, v, w = commands[:, 0], commands[:, 1], commands[:, 2]
        self.t, self.v, self.w = t, v, w
        dt = np.diff(t)
        theta = np.concatenate([[0.0], np.cumsum(w[:-1] * dt)])
        x, y = _arcs(v[:-1], w[:-1], theta[:-1], dt)
        self.pose = np.stack(
            [np.concatenate([[0.0], np.cumsum(x)]), np.concatenate([[0.0], np.cumsum(y)]), theta],
            axis=1,
        )

    def at(self, times: Array) -> Array:
        """Dead-reckoned poses (K, 3) at ``times`` (K,), in the frame of the first command."""
        times = np.asarray(times, dtype=float)
        i = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self.t) - 1)
        dt = np.maximum(times - self.t[i], 0.0)
        base = self.pose[i]
        x, y = _arcs(self.v[i], self.w[i], base[:, 2], dt)
        return np.stack([base[:, 0] + x, base[:, 1] + y, base[:, 2] + self.w[i] * dt], axis=1)

    def between(self, t0: Array, t1: Array) -> Array:
        """The motion (K, 3) from time t0 to t1 in the robot's frame at t0: x forward, y left,
        θ wrapped to (−π, π]."""
        return relative(self.at(t0), self.at(t1))


def _arcs(v: Array, w: Array, theta: Array, dt: Array) -> tuple[Array, Array]:
    """World-frame displacement of arcs (v, ω) held for dt from heading θ."""
    straight = np.abs(w) < SMALL_OMEGA
    w_safe = np.where(straight, 1.0, w)
    end = theta + w * dt
    x = np.where(straight, v * dt * np.cos(theta), v / w_safe * (np.sin(end) - np.sin(theta)))
    y = np.where(straight, v * dt * np.sin(theta), v / w_safe * (np.cos(theta) - np.cos(end)))
    return x, y


def relative(a: Array, b: Array) -> Array:
    """a⁻¹ ∘ b for poses (K, 3): b in the frame of a, θ wrapped to (−π, π]."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    dtheta = np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dtheta], axis=1)


@dataclass(frozen=True, slots=True)
class Sightings:
    """One robot's measurements sorted: ``landmarks`` (N, 4) time, landmark subject, range,
    bearing; ``robots`` (N, 4) time, robot subject, range, bearing; ``misreads`` the number of
    rows whose barcode is in no row of ``Barcodes.dat``."""

    landmarks: Array
    robots: Array
    misreads: int


def sightings(data: MrclamDataset, log: RobotLog) -> Sightings:
    """``log``'s measurements by what their barcode names (a robot's own barcode, which it
    cannot see, counts as a misread)."""
    m = log.measurements
    subjects = np.array([data.barcodes.get(int(b), -1) for b in m[:, 1]], dtype=float)
    robot = (subjects >= 1) & (subjects <= ROBOTS) & (subjects != log.subject)
    landmark = np.isin(subjects, list(LANDMARK_SUBJECTS))
    rows = np.column_stack([m[:, 0], subjects, m[:, 2], m[:, 3]])
    return Sightings(rows[landmark], rows[robot], int((~robot & ~landmark).sum()))


# -- steps, and noise against Vicon -----------------------------------------------------------


def truth_at(log: RobotLog, times: Array) -> Array:
    """Vicon poses (K, 3) at ``times``, interpolated linearly (θ unwrapped first), θ wrapped to
    (−π, π]; for scoring and calibration only."""
    gt = log.groundtruth
    theta = np.interp(times, gt[:, 0], np.unwrap(gt[:, 3]))
    x, y = np.interp(times, gt[:, 0], gt[:, 1]), np.interp(times, gt[:, 0], gt[:, 2])
    return np.stack([x, y, np.angle(np.exp(1j * theta))], axis=1)


def step_times(data: MrclamDataset, rate: float) -> Array:
    """t₀ … t_K every 1/``rate`` s, within every robot's odometry and ground truth (the span all
    five cover); step k of a run ends at t_k."""
    if not rate > 0:
        raise ValueError(f"rate {rate} must be > 0 Hz")
    start = max(max(r.odometry[0, 0], r.groundtruth[0, 0]) for r in data.robots)
    end = min(min(r.odometry[-1, 0], r.groundtruth[-1, 0]) for r in data.robots)
    if end <= start:
        raise MrclamError("the robots' odometry and ground truth share no time span")
    return start + np.arange(math.floor((end - start) * rate) + 1) / rate


def odometry_increments(log: RobotLog, times: Array) -> Array:
    """The motion (K, 3) from t_{k−1} to t_k integrated from the velocity commands, in the
    robot's frame at t_{k−1}: what a run's step k reads as odometry."""
    return Odometry(log.odometry).between(times[:-1], times[1:])


def landmark_steps(log: RobotLog, landmarks: Array, times: Array) -> Array:
    """Landmark sightings (N, 5) as the steps see them: step k (1…K, the sighting's time in
    (t_{k−1}, t_k]), landmark subject, range, bearing in the robot's frame at t_k, and the
    time moved (t_k − t ≥ 0, at most 1/rate). The robot's motion over that time comes from its
    own odometry, so nothing but what the robot measured goes in. Sightings before t₀ or after
    t_K are left out."""
    t = landmarks[:, 0]
    keep = (t > times[0]) & (t <= times[-1])
    t, rows = t[keep], landmarks[keep]
    k = np.searchsorted(times, t, side="left")
    motion = Odometry(log.odometry).between(t, times[k])  # from t to t_k, in the frame at t
    r, b = rows[:, 2], rows[:, 3]
    p = np.stack([r * np.cos(b), r * np.sin(b), np.zeros_like(r)], axis=1)
    seen = relative(motion, p)  # the point in the frame at t_k
    return np.column_stack(
        [
            k,
            rows[:, 1],
            np.hypot(seen[:, 0], seen[:, 1]),
            np.arctan2(seen[:, 1], seen[:, 0]),
            times[k] - t,
        ]
    )


@dataclass(frozen=True, slots=True)
class Calibration:
    """Noise measured against Vicon: per step (at ``rate``) of odometry, σ of x, y, θ
    (``odometry``), and per landmark sighting σ of range and bearing (``range``, ``bearing``),
    each 1.4826 × the median absolute residual (robust to the few gross errors: ``outliers``,
    the share of residuals beyond 5 σ, and the plain standard deviations ``odometry_std``,
    ``range_std``, ``bearing_std`` say how few), the median residuals (``range_bias``,
    ``bearing_bias``: the σ are taken about them); ``steps`` and ``sightings`` the samples, over
    ``seconds`` from the start."""

    rate: float
    seconds: float
    steps: int
    sightings: int
    odometry: tuple[float, float, float]
    range: float
    bearing: float
    odometry_std: tuple[float, float, float]
    range_std: float
    bearing_std: float
    outliers: float
    range_bias: float  # the median range residual (measured − Vicon), m
    bearing_bias: float  # rad
    # Per-step variances of the odometry measured over ``window`` seconds: the mean square
    # residual of the motion over n steps, / n. Odometry errors are correlated in time (wheel
    # scale, slip), so the one-step variance understates how fast they accumulate (Dataset 7,
    # x: 5.5e-5 from one step, 2.75e-4 per step over 5 s windows); zeros when ``window`` is 0.
    odometry_rate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    window: float = 0.0


def calibrate(data: MrclamDataset, rate: float, seconds: float, window: float = 0.0) -> Calibration:
    """Odometry and range–bearing noise of every robot over the first ``seconds`` s of the
    common span (data a run should not then be scored on); ``window`` > 0: also the odometry's
    variance per step over windows of that many seconds (``Calibration.odometry_rate``)."""
    times = step_times(data, rate)
    times = times[times <= times[0] + seconds]
    if len(times) < 3:
        raise MrclamError(f"fewer than 3 steps in the first {seconds:g} s at {rate:g} Hz")
    odo_res, rb_res = [], []
    for log in data.robots:
        truth = relative(truth_at(log, times[:-1]), truth_at(log, times[1:]))
        odo_res.append(relative(truth, odometry_increments(log, times)))
        rows = sightings(data, log).landmarks
        rows = rows[(rows[:, 0] >= times[0]) & (rows[:, 0] <= times[-1])]
        pose = truth_at(log, rows[:, 0])
        marks = np.array([data.landmarks[int(j)] for j in rows[:, 1]]).reshape(-1, 2)
        at = relative(pose, np.column_stack([marks, np.zeros(len(marks))]))
        dr = rows[:, 2] - np.hypot(at[:, 0], at[:, 1])
        db = np.angle(np.exp(1j * (rows[:, 3] - np.arctan2(at[:, 1], at[:, 0]))))
        rb_res.append(np.column_stack([dr, db]))
    odo, rb = np.concatenate(odo_res), np.concatenate(rb_res)
    if not len(rb):
        raise MrclamError(f"no landmark sighting in the first {seconds:g} s")
    robust = 1.4826 * np.median(np.abs(odo - np.median(odo, axis=0)), axis=0)
    robust_rb = 1.4826 * np.median(np.abs(rb - np.median(rb, axis=0)), axis=0)
    far = np.concatenate(
        [
            (np.abs(odo) > 5 * np.maximum(robust, 1e-12)).ravel(),
            (np.abs(rb) > 5 * np.maximum(robust_rb, 1e-12)).ravel(),
        ]
    )
    return Calibration(
        rate,
        float(times[-1] - times[0]),
        len(odo),
        len(rb),
        (float(robust[0]), float(robust[1]), float(robust[2])),
        float(robust_rb[0]),
        float(robust_rb[1]),
        tuple(float(v) for v in odo.std(axis=0)),  # type: ignore[arg-type]
        float(rb[:, 0].std()),
        float(rb[:, 1].std()),
        float(far.mean()),
        float(np.median(rb[:, 0])),
        float(np.median(rb[:, 1])),
        _odometry_rate(data, times, window),
        window,
    )


def _odometry_rate(data: MrclamDataset, times: Array, window: float) -> tuple[float, float, float]:
    """E[residual²] of the odometry over n steps, against Vicon, / n per component, n the steps
    in ``window`` seconds, over back-to-back windows of every robot."""
    dt = float(times[1] - times[0])
    n = round(window / dt)
    if n < 1:
        return (0.0, 0.0, 0.0)
    start = times[:-n:n]
    if not len(start):
        raise MrclamError(f"the calibration is shorter than one window of {window:g} s")
    res = []
    for log in data.robots:
        truth = relative(truth_at(log, start), truth_at(log, start + n * dt))
        res.append(relative(truth, Odometry(log.odometry).between(start, start + n * dt)))
    # the mean square, not the variance about the mean: a bias (a wheel-scale error) is error
    # the zero-mean model has to hold, and it is what accumulates
    ms = (np.concatenate(res) ** 2).mean(axis=0) / n
    return (float(ms[0]), float(ms[1]), float(ms[2]))
