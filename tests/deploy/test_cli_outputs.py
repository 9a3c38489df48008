"""Where commands write (deploy/cli/outputs.py, README.md "Where commands write"), run as real
processes: outputs are checked before any work, a bad one is one line naming the option (exit 2)
that leaves nothing behind, an existing one is refused unless --force, and the "wrote" line
names the file written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from deploy.base.files import write_atomically

SEMFLEET = Path(sys.executable).with_name("semfleet")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def semfleet(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SEMFLEET), *args],
        capture_output=True,
        text=True,
        timeout=300,  # a guard against hangs, not a speed check
        cwd=cwd,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )


def usage_error(r: subprocess.CompletedProcess[str], fragment: str) -> None:
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("semfleet: error: "), r.stderr
    assert fragment in lines[0], lines[0]


def test_scenario_plot_of_an_unknown_format_is_one_line_and_writes_nothing(
    tmp_path: Path,
) -> None:
    r = semfleet("scenario", "plot", "paper", "-o", "t.xyz", cwd=tmp_path)
    usage_error(r, "--output t.xyz: .xyz is not a figure format (.png, .pdf, .svg)")
    assert list(tmp_path.iterdir()) == []


def test_classifier_fit_checks_its_plot_before_it_writes_the_model(tmp_path: Path) -> None:
    r = semfleet("classifier", "sample", "paper", "-n", "40", "-o", "s.csv", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = semfleet("classifier", "fit", "s.csv", "-o", "m.npz", "--plot", "m.xyz", cwd=tmp_path)
    usage_error(r, "--plot m.xyz: .xyz is not a figure format")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv"]  # no m.npz
    r = semfleet("classifier", "fit", "s.csv", "-o", "m.png", cwd=tmp_path)
    usage_error(r, "--plot m.png: the model file (--output) itself")


def test_an_output_under_a_file_is_one_line_naming_the_option(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("not a folder")
    r = semfleet("scenario", "generate", *GENERATE, "-o", "a-file/g.toml", cwd=tmp_path)
    usage_error(r, "--output a-file/g.toml: cannot write there (a-file is a file)")
    r = semfleet("study", "--scenario", "lanes:short", "--out", "a-file/study", cwd=tmp_path)
    usage_error(r, "--out a-file/study: cannot write there (a-file is a file)")


def test_scenario_plot_without_a_suffix_says_it_added_png(tmp_path: Path) -> None:
    r = semfleet("scenario", "plot", "paper", "-o", "truthfile", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout == "wrote truthfile.png (--output truthfile has no suffix: .png added)\n"
    assert [p.name for p in tmp_path.iterdir()] == ["truthfile.png"]
    assert (tmp_path / "truthfile.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize("typed", ["figures", "figures/"])
def test_scenario_plot_into_a_folder_names_the_figure_after_the_scenario(
    tmp_path: Path, typed: str
) -> None:
    if typed == "figures":
        (tmp_path / "figures").mkdir()
    r = semfleet("scenario", "plot", "lanes:short", "-o", typed, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout == f"wrote figures/lanes.png (--output {typed} is a folder)\n"
    assert [p.name for p in tmp_path.iterdir()] == ["figures"]  # no figures.png next to it
    assert (tmp_path / "figures" / "lanes.png").read_bytes()[:8] == PNG_MAGIC


GENERATE = ("--robots", "2", "--objects", "3", "--classes", "2", "--seed", "1", "--steps", "5")

# Every command that writes a file, with a small run of it; OUT is the file.
OUT = "out.png"
FILE_COMMANDS = {
    "scenario plot": ("scenario", "plot", "lanes:short", "-o", OUT),
    "scenario generate": ("scenario", "generate", *GENERATE, "-o", OUT),
    "scenario model": ("scenario", "model", "paper", "-o", OUT),
    "scenario frames": ("scenario", "frames", "paper", "--seed", "1", "--robot", "r1", "-o", OUT),
    "classifier sample": ("classifier", "sample", "paper", "-n", "5", "-o", OUT),
}


@pytest.mark.parametrize("name", FILE_COMMANDS)
def test_a_command_refuses_an_existing_file_unless_force(tmp_path: Path, name: str) -> None:
    args = FILE_COMMANDS[name]
    out = tmp_path / OUT
    out.write_text("keep me\n")
    usage_error(semfleet(*args, cwd=tmp_path), f"--output {OUT}: already exists (--force ")
    assert out.read_text() == "keep me\n"
    r = semfleet(*args, "--force", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert out.read_text(errors="replace") != "keep me\n"
    assert [p.name for p in tmp_path.iterdir()] == [OUT]  # no temporary file left


# Commands that write a folder (DIR): refused before anything starts (no run, agent or session).
DIR = "out"
FOLDER_COMMANDS = {
    "study": ("study", "--scenario", "lanes:short", "--runs", "1", "--out", DIR),
    "ufastslam": ("ufastslam", "--scenario", "rectangle", "--runs", "1", "--out", DIR),
    "launch": ("launch", "--scenario", "lanes:short", "--out", DIR),
    "chaos": ("chaos", "--scenario", "lanes:short", "--out", DIR),
    "chaos --attack": ("chaos", "--scenario", "lanes:short", "--attack", "all", "--out", DIR),
    "demo": ("demo", "--out", DIR),
    "fleet watch": ("fleet", "watch", "--connect", "tcp/127.0.0.1:9", "--fleet", "f", "--out", DIR),
}


@pytest.mark.parametrize("name", FOLDER_COMMANDS)
def test_a_command_refuses_a_folder_that_is_not_empty_before_it_starts(
    tmp_path: Path, name: str
) -> None:
    (tmp_path / DIR).mkdir()
    (tmp_path / DIR / "results.json").write_text("{}\n")
    r = semfleet(*FOLDER_COMMANDS[name], cwd=tmp_path)
    usage_error(r, f"--out {DIR}: exists and is not empty (--force writes over the outputs in it)")
    assert r.stdout == ""  # nothing started
    assert [p.name for p in (tmp_path / DIR).iterdir()] == ["results.json"]


def test_a_recording_is_refused_if_it_exists(tmp_path: Path) -> None:
    (tmp_path / "run.rrd").write_text("an earlier recording")
    r = semfleet("launch", "--scenario", "lanes:short", "--record", "run.rrd", cwd=tmp_path)
    usage_error(r, "--record run.rrd: already exists (--force overwrites it)")
    assert not (tmp_path / "out").exists()


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path: Path) -> None:
    out = tmp_path / "model.npz"
    out.write_text("old")

    def half_then_fail(tmp: Path) -> None:
        tmp.write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_atomically(out, half_then_fail)
    assert [p.name for p in tmp_path.iterdir()] == ["model.npz"]
    assert out.read_text() == "old"
    write_atomically(out, lambda tmp: tmp.write_text("new"))
    assert [p.name for p in tmp_path.iterdir()] == ["model.npz"]
    assert out.read_text() == "new"
