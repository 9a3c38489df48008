"""Every subcommand under bad values (issue 46, "Done when"): the walk takes each command of
the parser (`scenario show`, `fleet status`, …), each of its options and positionals, and gives
that one a bad value: a word where a number goes, a negative, NaN or infinite number, an unknown
choice, a path under a file (nothing can be read or written there); a command that needs
arguments is also given none. The command's required arguments get a path under a file too,
so that whatever is checked first fails and no case starts real work.

Every case must be a usage mistake: exit 2 and one line ``semfleet…: error: …`` on stderr,
with no Python traceback and no path from inside a dependency (site-packages, Zenoh's Rust
build). The cases run through :func:`deploy.cli.main.main` in this process (a subprocess each
would take minutes); the file descriptors are captured, so what a dependency writes to them
directly is seen too. The number of cases is printed and has a floor.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
from collections.abc import Iterator
from pathlib import Path
from types import FrameType

import pytest

from deploy.cli.main import build_parser, main

NUMBERS = ("x", "-1", "nan", "1e999")  # for an option with a type
LEAKS = ("Traceback", "site-packages", ".cargo", ".rs:", "/usr/lib/python")
CASE_S = 30  # no case may take longer: a value that was taken has started real work
MIN_CASES = 300  # the walk's size when it was written (a floor: new options add cases)


class Stalled(BaseException):
    """A case that ran past CASE_S (not an Exception: the launcher must not map it)."""


def leaf_commands(
    parser: argparse.ArgumentParser, words: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield words, parser
        return
    for name, sub in subs[0].choices.items():
        yield from leaf_commands(sub, (*words, name))


def takes_value(action: argparse.Action) -> bool:
    skip = (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)
    return not isinstance(action, skip) and action.nargs != 0


def bad_values(action: argparse.Action, under_a_file: str) -> list[str]:
    if action.choices is not None:
        return ["nonesuch"]
    if action.type in (None, str, Path):
        return [under_a_file]
    return list(NUMBERS)


def argv_with(
    words: tuple[str, ...],
    parser: argparse.ArgumentParser,
    action: argparse.Action,
    value: str,
    filler: str,
) -> list[str]:
    """``words``, ``action`` given ``value``, every other required argument ``filler``."""
    argv = [*words]
    for other in parser._actions:
        if not takes_value(other) or not (other is action or other.required):
            continue
        given = value if other is action else filler
        argv += [other.option_strings[0], given] if other.option_strings else [given]
    return argv


def cases(under_a_file: str) -> list[list[str]]:
    """Every command with no argument, then with each argument given each bad value."""
    found = []
    for words, parser in leaf_commands(build_parser()):
        if any(a.required for a in parser._actions if takes_value(a)):
            found.append([*words])
        for action in parser._actions:
            if takes_value(action):
                for value in bad_values(action, under_a_file):
                    found.append(argv_with(words, parser, action, value, under_a_file))
    return found


@contextlib.contextmanager
def time_limit(seconds: int) -> Iterator[None]:
    def stalled(_signum: int, _frame: FrameType | None) -> None:
        raise Stalled

    previous = signal.signal(signal.SIGALRM, stalled)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def run_case(argv: list[str]) -> tuple[int | str, str]:
    """(exit code, or what went wrong instead) of ``semfleet ARGV``."""
    try:
        with time_limit(CASE_S):
            return main(argv), ""
    except SystemExit as exc:  # argparse's own errors
        return (exc.code if isinstance(exc.code, int) else 1), ""
    except Stalled:
        return f"still running after {CASE_S} s", ""
    except Exception as exc:  # a bug: the launcher kept its traceback
        return "Traceback", f"{type(exc).__name__}: {exc}"


def test_every_subcommand_refuses_bad_values_in_one_line_without_a_traceback(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "a-file").write_text("not a folder\n")
    monkeypatch.chdir(tmp_path)  # a relative default (out/…) would land here, and be refused
    walk = cases(str(tmp_path / "a-file" / "x"))
    failures = []
    for argv in walk:
        code, bug = run_case(argv)
        out, err = capfd.readouterr()
        lines = err.strip().splitlines()
        one_line = len(lines) == 1 and lines[0].startswith("semfleet") and ": error: " in lines[0]
        leaks = [leak for leak in LEAKS if leak in out + err]
        if code != 2 or not one_line or leaks or bug:
            failures.append(f"semfleet {' '.join(argv)}: exit {code} {bug} {leaks} {err!r}")
    commands = list(leaf_commands(build_parser()))
    print(f"{len(walk)} cases of bad input over {len(commands)} commands")
    assert not failures, f"{len(failures)} of {len(walk)} cases:\n" + "\n".join(failures)
    assert len(walk) >= MIN_CASES, len(walk)
    assert not list(tmp_path.rglob("*.json")), "a case wrote results"
