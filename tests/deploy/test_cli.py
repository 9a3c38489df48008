"""The `semfleet` command, run as a real process: outputs, files written and exit codes; and its
launcher in process: the project's own errors are one line with exit 2 (usage, configuration) or 1
(run time), anything else keeps its traceback."""

from __future__ import annotations

import argparse
import errno
import importlib.metadata
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from rich.console import Console

from agents.journal import JournalError
from deploy.base.errors import RunFailure, UsageError
from deploy.cli.commands import demo as demo_cmd
from deploy.cli.main import build_parser, exit_code, main
from deploy.launch import LaunchError
from deploy.launch.conductor import ConductorError
from deploy.operator.agent_config import AgentConfigError
from deploy.study.runner import run_seeded
from deploy.study.types import StudyError
from estimator.distributed import SlotError
from protocol.errors import LocalProtocolError, MalformedMessage
from sim.scenario import ScenarioError

ROOT = Path(__file__).resolve().parents[2]
SEMFLEET = Path(sys.executable).with_name("semfleet")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def semfleet(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SEMFLEET), *args],
        capture_output=True,
        text=True,
        timeout=600,  # a guard against hangs, not a speed check
        cwd=cwd,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )


def test_console_script_installed() -> None:
    assert SEMFLEET.exists(), f"{SEMFLEET} missing: is the package installed (pip install -e .)?"


def test_scenario_show_paper_lists_robots_sightings_and_edges() -> None:
    r = semfleet("scenario", "show", "paper")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for text in ("r1", "r2", "r3", "first sighting", "k = 1", "k = 3", "r2–r3", "6–60", "13–60"):
        assert text in out, text
    # object 7 is only ever seen by r1, first at step 1
    assert "r1@1" in out
    assert "\x1b[" not in out  # piped: plain text, no colours or cursor moves


def test_piped_output_is_plain_even_when_the_terminal_variables_say_colour() -> None:
    r = subprocess.run(
        [str(SEMFLEET), "scenario", "show", "lanes:short"],
        capture_output=True,
        text=True,
        env={"PATH": "/usr/bin:/bin", "TERM": "xterm-256color", "COLUMNS": "80"},
    )
    assert r.returncode == 0 and "\x1b[" not in r.stdout, r.stdout[:300]
    assert max(len(line) for line in r.stdout.splitlines()) <= 80


def test_scenario_show_applies_variants_and_overrides() -> None:
    r = semfleet("scenario", "show", "paper", "--variant", "comm10", "--set", "sensor.range=10")
    assert r.returncode == 0, r.stderr
    assert "variants applied: comm10" in r.stdout
    assert "50°, 10 m" in r.stdout
    assert "mode range" in r.stdout


def test_scenario_show_header_is_the_world_after_variants_and_set() -> None:
    args = ("scenario", "show", "paper", "--variant", "sense10", "--set", "sensor.range=5")
    r = semfleet(*args)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0] == "paper (paper.toml, variants applied: sense10; --set sensor.range=5)"
    assert "sensing: 50°, 5 m (half angle, range; every robot)" in lines
    # The file's description (its "sensing 3.5 m") is said to be the file's, not the world's.
    said = [line for line in lines if "3.5 m" in line]
    assert said and all(
        line.startswith("the file's description, before variants and --set: ") for line in said
    )
    plain = semfleet("scenario", "show", "paper").stdout.splitlines()
    assert plain[0] == "paper (paper.toml, variants applied: none)"
    assert plain[1].startswith("3 robots, 15 objects") and "sensing: 50°, 3.5 m" in plain[4]


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["scenario", "show", "nonexistent.toml"], "nonexistent.toml: no such scenario file"),
        (["scenario", "show", "nonesuch"], "not a file and not a bundled scenario"),
        (["scenario", "show", "paper", "--variant", "nope"], "no variant 'nope'"),
        (["scenario", "show", "paper", "--set", "sensor.range=-1"], "sensor.range: -1 must be > 0"),
        (["scenario", "show", "paper", "--set", "bogus"], "expected FIELD=VALUE"),
        (["scenario", "plot", "paper", "-o", "x.png", "--cones", "99"], "outside 0..60"),
    ],
)
def test_cli_user_errors_are_one_clear_line(tmp_path: Path, args: list[str], fragment: str) -> None:
    r = semfleet(*args, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert fragment in r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0, r.stderr


def test_cli_bad_scenario_file_names_the_field(tmp_path: Path) -> None:
    text = (Path(__file__).parents[2] / "sim" / "scenarios" / "paper.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(
        text.replace(
            "id = 15\npose = [-2.5, 2.0, 0.0]\nclass = 2",
            "id = 15\npose = [-2.5, 2.0, 0.0]\nclass = 3",
        )
    )
    r = semfleet("scenario", "show", str(bad))
    assert r.returncode == 2
    assert f"{bad}: objects[14].class: 3 is out of range 1..2" in r.stderr


def test_scenario_plot_writes_png(tmp_path: Path) -> None:
    out = tmp_path / "sub" / "truth.png"
    r = semfleet("scenario", "plot", "paper", "-o", str(out), "--cones", "1", "30")
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert out.stat().st_size > 20_000


def test_scenario_plot_default_cones_fit_a_world_shorter_than_60_steps(tmp_path: Path) -> None:
    out = tmp_path / "short.png"
    r = semfleet("scenario", "plot", "lanes:short", "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:8] == PNG_MAGIC


def test_scenario_generate_then_show(tmp_path: Path) -> None:
    out = tmp_path / "world.toml"
    r = semfleet(
        "scenario",
        "generate",
        "--robots",
        "4",
        "--objects",
        "25",
        "--classes",
        "3",
        "--seed",
        "5",
        "-o",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    shown = semfleet("scenario", "show", str(out))
    assert shown.returncode == 0, shown.stderr
    assert "random-r4-o25-c3-s5" in shown.stdout
    again = tmp_path / "again.toml"
    semfleet(
        "scenario",
        "generate",
        "--robots",
        "4",
        "--objects",
        "25",
        "--classes",
        "3",
        "--seed",
        "5",
        "-o",
        str(again),
    )
    assert again.read_text() == out.read_text()


def test_scenario_generate_rejects_bad_arguments(tmp_path: Path) -> None:
    r = semfleet(
        "scenario",
        "generate",
        "--robots",
        "0",
        "--objects",
        "5",
        "--classes",
        "2",
        "--seed",
        "1",
        "-o",
        str(tmp_path / "x.toml"),
    )
    assert r.returncode == 2
    assert "must be a positive integer" in r.stderr


def test_demo_launches_three_agents_over_zenoh_and_prints_the_final_table(tmp_path: Path) -> None:
    r = semfleet("demo", "--out", str(tmp_path / "demo"))
    assert r.returncode == 0, r.stderr
    assert "launching 3 agent processes" in r.stdout
    assert "final step k = 60" in r.stdout
    demo = tmp_path / "demo"
    for png in ("paper-ground-truth.png", "msde.png", "robot_error.png"):
        assert (demo / png).read_bytes()[:8] == PNG_MAGIC, png
    doc = json.loads((demo / "results.json").read_text())
    assert set(doc["methods"]) == {"local", "distributed"}
    assert doc["demo"] is True and doc["launch"]["mode"] == "lockstep", doc["launch"]
    assert 0 < doc["launch"]["wall_s"] < 600  # docs/results.md: a launch's settings
    assert "insecure fleet: plain Zenoh, no TLS or access control" in r.stdout
    final = {m: doc["methods"][m]["mean"]["msde"][-1] for m in ("local", "distributed")}
    assert final["distributed"] < final["local"]  # the paper's result, seed 0
    for robot in ("r1", "r2", "r3"):  # every agent really ran as its own process, with a log
        assert "up at step 0" in (demo / "logs" / f"{robot}.log").read_text()


def test_launch_stack_gossip_reaches_every_agents_config(tmp_path: Path) -> None:
    r = semfleet(
        "launch", "--scenario", "paper", "--mode", "realtime", "--steps", "3",
        "--stack-gossip", "delta", "--relay", "tick", "--keep-slots", "2", "--out", "out",
        cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    for robot in ("r1", "r2", "r3"):  # not the defaults ("ask", "event", 64)
        text = (tmp_path / "out" / "agents" / f"{robot}.toml").read_text()
        assert 'stack_gossip = "delta"' in text and 'relay = "tick"' in text
        assert "keep_slots = 2" in text
    for value in ("1", "65", "all"):
        bad = semfleet("launch", "--scenario", "paper", "--keep-slots", value, cwd=tmp_path)
        assert bad.returncode == 2 and "--keep-slots:" in bad.stderr, bad.stderr
        assert len(bad.stderr.strip().splitlines()) <= 3, bad.stderr
    bad = semfleet("launch", "--scenario", "paper", "--stack-gossip", "rumour", cwd=tmp_path)
    assert bad.returncode == 2 and "--stack-gossip: invalid choice: 'rumour'" in bad.stderr
    bad = semfleet("launch", "--scenario", "paper", "--relay", "rumour", cwd=tmp_path)
    assert bad.returncode == 2 and "--relay: invalid choice: 'rumour'" in bad.stderr


# --------------------------------------------------------------------------- errors → exit codes


MAX = str(2**63 - 1)
GENERATE = ["scenario", "generate", "--robots", "1", "--objects", "2", "--classes", "2"]


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["study", "--scenario", "paper", "--seed", MAX, "--runs", "2"], "largest seed"),
        (["ufastslam", "--scenario", "rectangle", "--seed", MAX], "largest seed"),
        (["launch", "--scenario", "paper", "--robots", "r1,r9"], "--robots: unknown robots"),
        (["launch", "--scenario", "paper", "--steps", "61"], "--steps: 61 outside 1..60"),
        (["chaos", "--scenario", "paper", "--kill", "r9@3"], "--kill/--restart: unknown robot"),
        (
            ["chaos", "--scenario", "paper", "--attack", "all", "--stack-gossip", "ask"],
            "--stack-gossip: not with --attack",
        ),
        (
            ["launch", "--scenario", "paper", "--conductor-only", "--stack-gossip", "full"],
            "--stack-gossip: not with --conductor-only",
        ),
        (
            ["chaos", "--scenario", "paper", "--attack", "all", "--relay", "tick"],
            "--relay: not with",
        ),
        (
            ["launch", "--scenario", "paper", "--conductor-only", "--relay", "tick"],
            "--relay: not with --conductor-only",
        ),
        (
            ["chaos", "--scenario", "paper", "--attack", "all", "--keep-slots", "3"],
            "--keep-slots: not with",
        ),
        (
            ["launch", "--scenario", "paper", "--conductor-only", "--keep-slots", "3"],
            "--keep-slots: not with --conductor-only",
        ),
        (
            ["launch", "--scenario", "paper", "--advertise", "tcp/10.0.0.1:7447"],
            "--advertise: only",
        ),
        (["launch", "--scenario", "paper", "--agent-host", "b"], "--agent-host: only with --co"),
        (
            ["launch", "--scenario", "paper", "--conductor-only", "--agent-host", "b"],
            "only with --s",
        ),
        (["launch", "--scenario", "paper", "--conductor-only"], "--advertise ENDPOINT, the add"),
        (
            [
                "launch",
                "--scenario",
                "paper",
                "--conductor-only",
                "--secure",
                "--conductor-listen",
                "tcp/127.0.0.1:7447",
            ],
            "conductor listen tcp/127.0.0.1:7447: a secure fleet's endpoints are tls/",
        ),
    ],
)
def test_cli_usage_errors_exit_2_with_one_line(
    tmp_path: Path, args: list[str], fragment: str
) -> None:
    _usage_error(semfleet(*args, "--out", "out", cwd=tmp_path), fragment)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("host", ["a b", "lab-", "x" * 64, "host_b"])
def test_a_certificate_host_that_is_no_address_or_dns_name_is_a_usage_error(
    tmp_path: Path, host: str
) -> None:
    for args in (
        ["launch", "--scenario", "paper", "--conductor-only", "--secure", "--agent-host", host],
        ["fleet", "init", "--fleet", "f", "--robots", "r1", "--scenario", "paper", "--host", host],
    ):
        r = semfleet(*args, "--out" if args[0] == "launch" else "-o", "out", cwd=tmp_path)
        assert r.returncode == 2, (r.stdout, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "neither an IP address nor a DNS name" in lines[0], r.stderr
        assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--area", "-5"], "--area -5.0: must be a positive number of metres"),
        (["--area", "nan"], "--area nan: must be"),
        (["--comm-range", "0"], "--comm-range 0.0: must be"),
        (["--comm-range", "inf"], "--comm-range inf: must be"),
    ],
)
def test_scenario_generate_bad_sizes_are_usage_errors(
    tmp_path: Path, args: list[str], fragment: str
) -> None:
    r = semfleet(*GENERATE, "--seed", "1", *args, "-o", "out/g.toml", cwd=tmp_path)
    _usage_error(r, fragment)
    assert not (tmp_path / "out").exists()


def _usage_error(r: subprocess.CompletedProcess[str], fragment: str) -> None:
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("semfleet: error: "), r.stderr
    assert fragment in lines[0], lines[0]


def test_cli_output_path_under_a_file_is_a_usage_error(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("not a directory")
    r = semfleet("scenario", "plot", "paper", "-o", "a-file/x.png", cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stderr == (
        "semfleet: error: --output a-file/x.png: cannot write there (a-file is a file)\n"
    ), r.stderr


def _raising(exc: BaseException) -> Callable[[argparse.Namespace, Console], int]:
    def run(args: argparse.Namespace, console: Console) -> int:
        raise exc

    return run


KNOWN = [
    (UsageError("--x: must be positive"), 2),
    (RunFailure("agent r2 died"), 1),
    (RunFailure(), 1),
    (StudyError("run with seed 3 failed: a worker died"), 1),
    (LaunchError("agent r2 exited unexpectedly\n  with code -9"), 1),
    (ConductorError("agents ['r1'] did not come up within 90 s"), 1),
    (ScenarioError("x.toml: sensor.range: -1 must be > 0"), 2),
    (AgentConfigError(Path("a.toml"), "agent.mode", "'fast'"), 2),
    (JournalError("r1.log belongs to another run: identity 'seed' is 3", "seed"), 1),
    (LocalProtocolError("must be two finite numbers", "pos"), 1),
    (MalformedMessage("not msgpack"), 1),
    (FileNotFoundError(errno.ENOENT, "No such file or directory", "frames.jsonl"), 2),
    (PermissionError(errno.EACCES, "Permission denied", "out/results.json"), 2),
    (FileExistsError("out/model.toml: already exists (--force overwrites it)"), 2),
    (IsADirectoryError(errno.EISDIR, "Is a directory", "out"), 2),
    (NotADirectoryError(errno.ENOTDIR, "Not a directory", "a-file/x.png"), 2),
    (OSError(errno.ENOSPC, "No space left on device"), 1),
    (TimeoutError("no subscriber within 10 s"), 1),
]


@pytest.mark.parametrize(("exc", "code"), KNOWN, ids=[type(e).__name__ for e, _ in KNOWN])
def test_cli_known_errors_are_one_line_with_their_exit_code(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], exc: Exception, code: int
) -> None:
    monkeypatch.setattr(demo_cmd, "run", _raising(exc))
    assert main(["demo"]) == code
    message = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename:  # the path first, without the errno
        message = f"{exc.filename}: {exc.strerror}"
    assert capsys.readouterr().err == f"semfleet: error: {message}\n"


def test_cli_interrupt_is_one_line_exit_130(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(demo_cmd, "run", _raising(KeyboardInterrupt()))
    assert main(["demo"]) == 130
    assert capsys.readouterr().err == "semfleet: error: interrupted\n"


UNEXPECTED = [
    ValueError("a bug"),
    RuntimeError("a bug"),
    FloatingPointError("overflow encountered in exp"),
    KeyError("r9"),
    TypeError("a bug"),
    SlotError("a ValueError of the project that must never reach the CLI"),
]


@pytest.mark.parametrize("exc", UNEXPECTED, ids=[type(e).__name__ for e in UNEXPECTED])
def test_cli_unexpected_errors_keep_their_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], exc: Exception
) -> None:
    monkeypatch.setattr(demo_cmd, "run", _raising(exc))
    with pytest.raises(type(exc)) as caught:
        main(["demo"])
    assert caught.value is exc
    assert caught.traceback[-1].name == "run"  # re-raised as it was, from where it happened
    assert "semfleet: error" not in capsys.readouterr().err


def test_cli_unexpected_error_prints_its_traceback_from_a_real_process() -> None:
    script = (
        "import sys\n"
        "from deploy.cli import main as cli\nfrom deploy.cli.commands import demo\n"
        "def run(args, console):\n"
        "    raise ValueError('a bug in a command')\n"
        "demo.run = run\n"
        "sys.exit(cli.main(['demo']))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)},
    )
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert r.stderr.startswith("Traceback (most recent call last):"), r.stderr
    assert r.stderr.strip().splitlines()[-1] == "ValueError: a bug in a command"
    assert "semfleet: error" not in r.stderr


def test_study_worker_bug_keeps_its_traceback_and_names_the_seed() -> None:
    with pytest.raises(ValueError, match="invalid literal") as caught:
        run_seeded({3: (int, "not a number")}, jobs=1)
    assert caught.value.__notes__ == ["in the run with seed 3"]
    remote = str(caught.value.__cause__)  # the worker's own traceback, printed with it
    assert "Traceback" in remote and "ValueError: invalid literal" in remote
    assert exit_code(caught.value) is None


def test_study_dead_worker_is_a_one_line_run_failure() -> None:
    with pytest.raises(StudyError, match="run with seed 7 failed: ") as caught:
        run_seeded({7: (os._exit, 3)}, jobs=1)
    assert exit_code(caught.value) == 1


def test_version_prints_the_installed_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"semfleet {importlib.metadata.version('semfleet')}"


CLI = (sys.executable, "-m", "deploy.cli")


def test_verbose_shows_semfleet_debug_lines_only(tmp_path: Path) -> None:
    r = subprocess.run(
        [*CLI, "-v", "scenario", "plot", "paper", "-o", str(tmp_path / "p.png")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    assert "matplotlib" not in r.stderr and "PIL" not in r.stderr, r.stderr[:2000]


def test_scenario_generate_refuses_more_classes_than_a_scenario_may_have(tmp_path: Path) -> None:
    r = semfleet(*GENERATE, "--seed", "1", "--classes", "65", "-o", "g.toml", cwd=tmp_path)
    assert r.returncode == 2 and "65: need 2 to 64 classes" in r.stderr, r.stderr
    assert not (tmp_path / "g.toml").exists()


def test_scenario_generate_never_writes_a_file_it_cannot_read_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(
        "deploy.cli.commands.scenario.dump_scenario", lambda s: 'format = 1\nname = "x"\n'
    )
    out = tmp_path / "g.toml"
    code = main([*GENERATE, "--seed", "1", "-o", str(out)])
    assert code == 2 and not out.exists()
    assert "the generated world would not load" in capsys.readouterr().err


def test_the_study_command_the_demo_suggests_parses() -> None:
    args = build_parser().parse_args(shlex.split(demo_cmd.STUDY_HINT)[1:])
    assert args.scenario == "paper" and args.runs == 100


def test_study_refuses_an_unwritable_out_before_any_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_run(*args: object, **kwargs: object) -> None:
        raise AssertionError("a run started before --out was checked")

    monkeypatch.setattr("deploy.cli.commands.study.run_study", no_run)
    (tmp_path / "a-file").write_text("not a directory")
    out = tmp_path / "a-file" / "study"
    code = main(["study", "--scenario", "lanes:short", "--runs", "1", "--out", str(out)])
    assert code == 2
    assert f"--out {out}: cannot write there" in capsys.readouterr().err


def _children(pid: int) -> set[int]:
    """Every live descendant of ``pid`` (from /proc)."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    found: set[int] = set()
    frontier = {pid}
    while frontier:
        frontier = {c for c, p in parents.items() if p in frontier} - found
        found |= frontier
    return found


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_study_stopped_by_a_signal_leaves_no_worker_behind(
    tmp_path: Path, sig: signal.Signals
) -> None:
    """``study --jobs 2`` stopped while its workers run: one line, the signal's exit code, and
    neither a worker nor the resource tracker outlives it (they used to, with leaked
    semaphores)."""
    proc = subprocess.Popen(
        [
            str(SEMFLEET),
            *shlex.split("study --scenario lanes:short --runs 6 --jobs 2 --out"),
            str(tmp_path / "out"),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={"PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )
    deadline = time.monotonic() + 120
    while len(children := _children(proc.pid)) < 3 and time.monotonic() < deadline:
        time.sleep(0.1)  # the resource tracker and both workers
    assert len(children) >= 3, "the study's workers never started"
    time.sleep(1.0)  # well inside a run
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    assert err == f"semfleet: error: stopped by {sig.name}\n", err
    deadline = time.monotonic() + 10  # orphans would belong to init now: look them up by pid
    while (still := [p for p in children if Path(f"/proc/{p}").exists()]) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.1)
    assert not still, f"{still} outlived the study"


class _Exited(Exception):
    def __init__(self, code: int) -> None:
        self.code = code


@pytest.mark.parametrize("sessions", [0, 1])
def test_the_command_leaves_at_once_only_after_a_zenoh_session(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], sessions: int
) -> None:
    """A process that opened a Zenoh session exits through ``os._exit`` with the command's code
    and its output flushed (interpreter teardown can abort it: deploy.cli.main.entry); any other
    through ``sys.exit``, so that its cleanups run."""
    import deploy.cli.main as cli
    from agents.transport.zenoh_transport import ZenohTransport

    def exit_now(code: int) -> None:
        raise _Exited(code)

    monkeypatch.setattr(cli.os, "_exit", exit_now)
    monkeypatch.setattr(ZenohTransport, "sessions_opened", sessions)
    monkeypatch.setattr(sys, "argv", ["semfleet", "scenario", "show", "nosuchscenario"])
    with pytest.raises(_Exited if sessions else SystemExit) as left:
        cli.entry()
    assert left.value.code == 2  # a usage error's code, either way
    assert "nosuchscenario" in capsys.readouterr().err


def test_the_console_script_is_the_entry() -> None:
    (script,) = [
        e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == "semfleet"
    ]
    assert script.value == "deploy.cli.main:entry"


def test_a_generated_world_of_point_objects_runs_through_a_study(tmp_path: Path) -> None:
    """``--kind point`` (issue 44): point landmarks by bearing and range, in the file and through
    ``study``'s local, distributed and centralized beliefs."""
    world = tmp_path / "points.toml"
    args = ("--robots", "3", "--objects", "12", "--classes", "3", "--seed", "4", "--steps", "20")
    r = semfleet("scenario", "generate", *args, "--kind", "point", "-o", str(world))
    assert r.returncode == 0, r.stderr
    text = world.read_text()
    assert 'objects = "point"' in text and "geometric_var = [0.01, 0.1]" in text
    out = tmp_path / "study"
    methods = "local,distributed,centralized"
    r = semfleet(
        "study", "--scenario", str(world), "--runs", "1", "--methods", methods, "--out", str(out)
    )
    assert r.returncode == 0, r.stderr
    assert (out / "results.json").exists()
