"""The MRCLAM reader (sim.mrclam): a small synthetic dataset in the MRCLAM format, whose robots
drive known arcs, read back exactly; odometry integrated along the arcs recovers the true motion;
every kind of broken file is named with its row; the shared Dataset 7 where present."""

from __future__ import annotations

import functools
import os
import tarfile
from pathlib import Path

import numpy as np
import pytest

from sim.mrclam import (
    MrclamError,
    Odometry,
    calibrate,
    landmark_steps,
    odometry_increments,
    read_mrclam,
    relative,
    sightings,
    step_times,
    truth_at,
)

HEADER = "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\n# test\n"
# The shared copy next to the repository, or SEMFLEET_MRCLAM: a folder holding the archive.
SHARED = Path(
    os.environ.get(
        "SEMFLEET_MRCLAM", Path(__file__).resolve().parents[3] / "shared" / "data" / "mrclam"
    )
)
T0 = 1_248_446_182.0
BARCODES = {1: 5, 2: 14, 3: 41, 4: 32, 5: 23, **{s: 60 + s for s in range(6, 21)}}


def _commands(subject: int) -> np.ndarray:
    """Velocity commands at uneven times: arcs of either sign, a straight stretch, a stop."""
    rng = np.random.default_rng(subject)
    t = T0 + np.cumsum(rng.uniform(0.01, 0.03, 400))
    v = np.where(np.arange(400) % 97 < 80, 0.2 + 0.1 * np.sin(np.arange(400) / 30), 0.0)
    w = np.where((np.arange(400) // 50) % 3 == 0, 0.0, 0.6 * np.cos(np.arange(400) / 40 + subject))
    return np.column_stack([t, v, w])


def _truth(commands: np.ndarray, start: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Poses at ``times`` by integrating the commands in fine Euler steps (an independent
    integrator), from ``start``."""
    out = []
    pose = start.astype(float).copy()
    base = commands[0, 0]  # times relative to it: t += h at 1.2·10⁹ s would lose 0.2 % per step
    commands = np.column_stack([commands[:, 0] - base, commands[:, 1:]])
    t = 0.0
    i = 0
    for target in times - base:
        while t < target - 1e-12:
            while i + 1 < len(commands) and commands[i + 1, 0] <= t + 1e-12:
                i += 1
            end = commands[i + 1, 0] if i + 1 < len(commands) else np.inf
            h = min(5e-4, target - t, end - t)
            v, w = commands[i, 1], commands[i, 2]
            mid = pose[2] + 0.5 * w * h
            pose += [v * h * np.cos(mid), v * h * np.sin(mid), w * h]
            t += h
        out.append(pose.copy())
    return np.array(out)


def _write(folder: Path, rows: dict[str, list[list[float]]]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, table in rows.items():
        body = "".join(" \t".join(f"{v:.9f}" for v in row) + "\n" for row in table)
        (folder / name).write_text(HEADER + body)


@functools.cache
def _rows() -> dict[str, list[list[float]]]:
    return _make_rows()


def _dataset(folder: Path) -> dict[str, list[list[float]]]:
    rows = _rows()
    _write(folder, rows)
    return rows


def _make_rows() -> dict[str, list[list[float]]]:
    """Five robots and 15 landmarks; each robot measures landmarks 6–8, robot 2 and an unknown
    barcode 99 at its own times."""
    rng = np.random.default_rng(0)
    landmarks = {s: rng.uniform(-4, 4, 2) for s in range(6, 21)}
    rows: dict[str, list[list[float]]] = {
        "Barcodes.dat": [[s, b] for s, b in BARCODES.items()],
        "Landmark_Groundtruth.dat": [[s, *p, 1e-4, 1e-4] for s, p in landmarks.items()],
    }
    for r in range(1, 6):
        cmd = _commands(r)
        start = np.array([r - 3.0, 0.5 * r, 0.3 * r])
        gt_t = np.arange(cmd[0, 0], cmd[-1, 0], 0.05)
        gt = _truth(cmd, start, gt_t)
        m_t = cmd[0, 0] + np.linspace(0.1, 0.9, 12) * (cmd[-1, 0] - cmd[0, 0])
        poses = _truth(cmd, start, m_t)
        meas = []
        for t, p, target in zip(m_t, poses, [6, 7, 8, 2, 99, 6] * 2, strict=True):
            where = landmarks.get(target, np.array([0.0, 0.0]))
            d = relative(p[None], np.array([[*where, 0.0]]))[0]
            meas.append([t, BARCODES.get(target, 99), np.hypot(d[0], d[1]), np.arctan2(d[1], d[0])])
        rows[f"Robot{r}_Groundtruth.dat"] = [[t, *p] for t, p in zip(gt_t, gt, strict=True)]
        rows[f"Robot{r}_Odometry.dat"] = cmd.tolist()
        rows[f"Robot{r}_Measurement.dat"] = meas
    return rows


def test_a_synthetic_dataset_reads_back_and_its_odometry_recovers_the_true_motion(
    tmp_path: Path,
) -> None:
    rows = _dataset(tmp_path / "MRCLAM_Synthetic")
    data = read_mrclam(tmp_path / "MRCLAM_Synthetic")
    assert data.name == "MRCLAM_Synthetic" and len(data.robots) == 5
    assert data.barcodes[41] == 3 and data.robot_barcodes() == {5: 1, 14: 2, 41: 3, 32: 4, 23: 5}
    assert len(data.landmarks) == 15
    for log in data.robots:
        np.testing.assert_allclose(log.odometry, rows[f"Robot{log.subject}_Odometry.dat"])
        odo = Odometry(log.odometry)
        gt = log.groundtruth
        # Over 0.5 s windows the integrated commands give the true relative motion (to the
        # fine Euler integration's accuracy and the 9 decimals written).
        a, b = np.arange(0, len(gt) - 10, 7), np.arange(10, len(gt), 7)
        got = odo.between(gt[a, 0], gt[b, 0])
        want = relative(gt[a, 1:], gt[b, 1:])
        np.testing.assert_allclose(got, want, atol=2e-6)
        s = sightings(data, log)
        # Its own barcode, which a robot cannot see, is a misread like the unknown one.
        own = log.subject == 2
        assert len(s.landmarks) == 8 and s.misreads == (4 if own else 2)
        assert len(s.robots) == (0 if own else 2)
        assert set(s.landmarks[:, 1]) == {6.0, 7.0, 8.0}
        # Each landmark sighting points at the landmark from the true pose at its time.
        pose = _truth(log.odometry, gt[0, 1:], s.landmarks[:, 0])
        r, bearing = s.landmarks[:, 2], s.landmarks[:, 3]
        seen = pose[:, :2] + r[:, None] * np.column_stack(
            [np.cos(pose[:, 2] + bearing), np.sin(pose[:, 2] + bearing)]
        )
        truth = np.array([data.landmarks[int(j)] for j in s.landmarks[:, 1]])
        np.testing.assert_allclose(seen, truth, atol=1e-5)


def test_odometry_stands_before_its_first_command_and_integrates_an_arc_exactly() -> None:
    odo = Odometry(np.array([[10.0, 1.0, 0.5], [12.0, 0.0, 0.0], [13.0, 0.0, 0.0]]))
    np.testing.assert_allclose(odo.at(np.array([5.0, 10.0])), np.zeros((2, 3)))
    # An arc of radius 2 through 1 rad: chord 2·2·sin(0.5) at heading 0.5.
    chord = 4 * np.sin(0.5)
    np.testing.assert_allclose(
        odo.at(np.array([12.0]))[0], [chord * np.cos(0.5), chord * np.sin(0.5), 1.0], atol=1e-12
    )
    np.testing.assert_allclose(odo.between(np.array([12.0]), np.array([13.0])), np.zeros((1, 3)))


def test_the_archive_as_shipped_reads_the_same(tmp_path: Path) -> None:
    _dataset(tmp_path / "MRCLAM_Synthetic")
    archive = tmp_path / "MRCLAM_Synthetic.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(tmp_path / "MRCLAM_Synthetic", arcname="MRCLAM_Synthetic")
    a, b = read_mrclam(tmp_path / "MRCLAM_Synthetic"), read_mrclam(archive)
    assert a.name == b.name and a.barcodes == b.barcodes and a.landmarks == b.landmarks
    for x, y in zip(a.robots, b.robots, strict=True):
        np.testing.assert_array_equal(x.measurements, y.measurements)


@pytest.mark.parametrize(
    "file, change, message",
    [
        ("Robot3_Odometry.dat", None, "Robot3_Odometry.dat: missing"),
        ("Robot2_Measurement.dat", "1.0 2.0 3.0", r"Robot2_Measurement.dat: row 15: expected 4"),
        ("Robot2_Measurement.dat", "1.0 x 3.0 4.0", r"row 15: not a number in '1.0 x 3.0 4.0'"),
        ("Robot2_Measurement.dat", "1.0 nan 3.0 4.0", r"row 15: a number that is not finite"),
        ("Robot4_Groundtruth.dat", "1.0 2.0 3.0 4.0", r"Robot4_Groundtruth.dat: row 4: time 1"),
        ("Barcodes.dat", "6 5", r"Barcodes.dat: row 23: subject 6 or barcode 5 repeated"),
        ("Barcodes.dat", "2.5 99", r"Barcodes.dat: row 23: 2.5 is not a subject"),
        ("Landmark_Groundtruth.dat", "3 1 1 0 0", r"row 18: subject 3 is not a landmark"),
    ],
)
def test_a_broken_file_is_named_with_its_row(
    tmp_path: Path, file: str, change: str | None, message: str
) -> None:
    folder = tmp_path / "d"
    _dataset(folder)
    path = folder / file
    if change is None:
        path.unlink()
    elif file.endswith("Groundtruth.dat") and file.startswith("Robot"):
        lines = path.read_text().splitlines()
        lines.insert(3, change)  # an early time after a later one
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_text(path.read_text() + change + "\n")
    with pytest.raises(MrclamError, match=message):
        read_mrclam(folder)


def test_what_is_not_a_dataset_says_so(tmp_path: Path) -> None:
    with pytest.raises(MrclamError, match="no such folder or archive"):
        read_mrclam(tmp_path / "absent")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(MrclamError, match=r"not a folder nor a \.tar\.xz archive"):
        read_mrclam(tmp_path / "x.txt")
    (tmp_path / "y.tar.xz").write_bytes(b"not xz at all")
    with pytest.raises(MrclamError, match=r"y\.tar\.xz: not a readable \.tar\.xz archive"):
        read_mrclam(tmp_path / "y.tar.xz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(MrclamError, match=r"Barcodes\.dat: missing"):
        read_mrclam(tmp_path / "empty")


@pytest.mark.skipif(
    not (SHARED / "MRCLAM_Dataset7.tar.xz").exists(),
    reason=f"the shared MRCLAM Dataset 7 is not at {SHARED}",
)
def test_dataset_7_as_shipped() -> None:
    data = read_mrclam(SHARED / "MRCLAM_Dataset7.tar.xz")
    assert [r.subject for r in data.robots] == [1, 2, 3, 4, 5] and len(data.landmarks) == 15
    r1 = data.robots[0]
    assert len(r1.measurements) == 3228  # the README's count
    s = sightings(data, r1)
    assert 600 <= len(s.robots) <= 700  # "about 650" robot sightings
    assert set(s.landmarks[:, 1].astype(int)) == set(range(6, 21))  # robot 1 sees all 15
    for log in data.robots:
        gt = log.groundtruth
        assert gt[0, 0] == pytest.approx(1248446182.116, abs=0.01)
        assert gt[-1, 0] == pytest.approx(1248447082.106, abs=0.01)
        # Real odometry against Vicon over 0.5 s: the median error is a few millimetres.
        odo = Odometry(log.odometry)
        t = np.arange(gt[0, 0] + 20, gt[-1, 0] - 20, 0.5)
        pose = np.array([np.interp(t, gt[:, 0], gt[:, i]) for i in (1, 2)]).T
        theta = np.interp(t, gt[:, 0], np.unwrap(gt[:, 3]))
        want = relative(np.column_stack([pose, theta])[:-1], np.column_stack([pose, theta])[1:])
        got = odo.between(t[:-1], t[1:])
        error = np.hypot(*(got[:, :2] - want[:, :2]).T)
        print(f"robot {log.subject}: odometry vs Vicon over 0.5 s: median {np.median(error):.4f} m")
        assert np.median(error) < 0.02


def test_steps_odometry_and_sightings_at_steps(tmp_path: Path) -> None:
    _dataset(tmp_path / "d")
    data = read_mrclam(tmp_path / "d")
    times = step_times(data, 2.0)
    assert np.allclose(np.diff(times), 0.5)
    assert times[0] >= max(r.odometry[0, 0] for r in data.robots)
    assert times[-1] <= min(r.groundtruth[-1, 0] for r in data.robots)
    for log in data.robots:
        gt = log.groundtruth
        np.testing.assert_allclose(truth_at(log, gt[::9, 0]), gt[::9, 1:], atol=1e-9)
        exact = _truth(log.odometry, gt[0, 1:], times)
        truth = relative(exact[:-1], exact[1:])
        np.testing.assert_allclose(odometry_increments(log, times), truth, atol=1e-5)
        rows = sightings(data, log).landmarks
        steps = landmark_steps(log, rows, times)
        inside = (rows[:, 0] > times[0]) & (rows[:, 0] <= times[-1])
        assert len(steps) == inside.sum() > 0
        k = steps[:, 0].astype(int)
        assert ((times[k - 1] < rows[inside, 0]) & (rows[inside, 0] <= times[k])).all()
        assert ((steps[:, 4] >= 0) & (steps[:, 4] <= 0.5)).all()
        # Each sighting, moved to its step's frame, points at the landmark from the true pose
        # at t_k.
        pose = _truth(log.odometry, log.groundtruth[0, 1:], times[k])
        r, b = steps[:, 2], steps[:, 3]
        seen = pose[:, :2] + r[:, None] * np.column_stack(
            [np.cos(pose[:, 2] + b), np.sin(pose[:, 2] + b)]
        )
        truth_xy = np.array([data.landmarks[int(j)] for j in steps[:, 1]])
        np.testing.assert_allclose(seen, truth_xy, atol=1e-4)


def test_calibration_recovers_the_noise_put_in(tmp_path: Path) -> None:
    """Range and bearing with known noise (and 2 % gross errors), exact odometry."""
    rows = {name: [list(r) for r in table] for name, table in _rows().items()}
    rng = np.random.default_rng(3)
    data = read_mrclam(_write_noisy(tmp_path / "n", rows, rng, 0.05, 0.02))
    cal = calibrate(data, 2.0, 1e6)
    assert cal.sightings > 1000
    # 1.4826 MAD over about 5,000 residuals: within 2 % (1 SE) of σ, plus about 2.5 % from the
    # gross errors it does not wholly ignore.
    assert cal.range == pytest.approx(0.05, rel=0.08) and cal.bearing == pytest.approx(
        0.02, rel=0.08
    )
    assert cal.range_bias == pytest.approx(0.03, abs=0.01)  # the bias put in
    assert max(cal.odometry) < 1e-4  # exact commands
    assert cal.range_std > cal.range  # the gross errors, which the robust σ leaves out
    assert 0.005 < cal.outliers < 0.03


def _write_noisy(
    folder: Path, rows: dict[str, list[list[float]]], rng: np.random.Generator, sr: float, sb: float
) -> Path:
    """``rows`` with every robot measuring 1,000 times in all, range biased by 3 cm and with
    noise σ ``sr``, bearing noise ``sb``; 2 % of ranges off by 2 m."""
    landmarks = {int(r[0]): np.array(r[1:3]) for r in rows["Landmark_Groundtruth.dat"]}
    for r in range(1, 6):
        cmd = np.array(rows[f"Robot{r}_Odometry.dat"])
        start = np.array(rows[f"Robot{r}_Groundtruth.dat"][0][1:])
        times = np.sort(rng.uniform(cmd[0, 0] + 0.2, cmd[-1, 0] - 0.2, 1000))
        poses = _truth(cmd, start, times)
        meas = []
        for t, p in zip(times, poses, strict=True):
            s = int(rng.integers(6, 21))
            d = relative(p[None], np.array([[*landmarks[s], 0.0]]))[0]
            rng_m = (
                np.hypot(d[0], d[1])
                + 0.03
                + sr * rng.normal()
                + (2.0 if rng.random() < 0.02 else 0)
            )
            meas.append([t, BARCODES[s], rng_m, np.arctan2(d[1], d[0]) + sb * rng.normal()])
        rows[f"Robot{r}_Measurement.dat"] = meas
    _write(folder, rows)
    return folder


@pytest.mark.skipif(
    not (SHARED / "MRCLAM_Dataset7.tar.xz").exists(),
    reason=f"the shared MRCLAM Dataset 7 is not at {SHARED}",
)
def test_dataset_7_calibrates_on_its_first_300_s() -> None:
    data = read_mrclam(SHARED / "MRCLAM_Dataset7.tar.xz")
    cal = calibrate(data, 2.0, 300.0)
    print(cal)
    assert cal.steps == 5 * 600 and cal.sightings > 5000
    assert 0.05 < cal.range < 0.3 and 0.003 < cal.bearing < 0.03
    assert max(cal.odometry[:2]) < 0.02 and cal.odometry[2] < 0.05


def test_the_odometry_rate_over_windows_sees_errors_that_accumulate(tmp_path: Path) -> None:
    """A wheel-scale error (every forward velocity 5 % long) is one error repeated every step:
    over windows of n steps its residual grows as n, its variance as n², so the variance per
    step over windows is about n times the one-step one, where white noise would give the
    same."""
    rows = {name: [list(r) for r in table] for name, table in _rows().items()}
    for r in range(1, 6):
        rows[f"Robot{r}_Odometry.dat"] = [
            [t, 1.05 * v, w] for t, v, w in rows[f"Robot{r}_Odometry.dat"]
        ]
    _write(tmp_path / "scaled", rows)
    data = read_mrclam(tmp_path / "scaled")
    cal = calibrate(data, 4.0, 1e6, window=2.5)  # windows of 10 steps
    assert cal.window == 2.5
    one_step = cal.odometry_std[0] ** 2
    assert cal.odometry_rate[0] > 4 * one_step, (cal.odometry_rate, one_step)
    exact = calibrate(
        read_mrclam(
            _write_noisy(
                tmp_path / "n",
                {n: [list(r) for r in t] for n, t in _rows().items()},
                np.random.default_rng(3),
                0.05,
                0.02,
            )
        ),
        4.0,
        1e6,
        window=2.5,
    )
    assert max(exact.odometry_rate) < 1e-8  # exact commands: nothing accumulates
