"""The ``semfleet`` command: one parser, one launcher that maps errors to exit codes.

The launcher prints the project's own errors as one line, ``semfleet: error: <message>``, and
exits 2 for a usage or configuration mistake, 1 for a failure at run time (see
:data:`KNOWN_ERRORS`). Any other exception is a bug: it keeps its traceback (exit 1, from Python).
"""

from __future__ import annotations

# The BLAS thread variables are pinned by the ``deploy`` package itself (deploy/__init__.py),
# which Python imports before this module.
import argparse
import importlib.metadata
import logging
import os
import signal
import sys
import threading
from collections.abc import Sequence
from typing import Any, NoReturn

from agents.journal import JournalError
from agents.transport.base import TransportError
from deploy.base.errors import (
    EXIT_FAILURE,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    CommandError,
    SignalExit,
)
from deploy.base.output import make_console
from deploy.cli.commands import (
    agent,
    classifier,
    dataset,
    demo,
    fleet,
    replay,
    router,
    scenario,
    study,
    ufastslam,
)
from deploy.cli.commands import export as export_command
from deploy.cli.commands import launch as launch_command
from deploy.launch import LaunchError
from deploy.launch.conductor import ConductorError
from deploy.operator.agent_config import AgentConfigError
from protocol.errors import ProtocolError
from sim.scenario import ScenarioError

# The project's error types raised outside deploy.base.errors' hierarchy, and their exit codes; an
# exception maps by the first of its classes (most specific first) found here. deploy's own
# command errors are CommandErrors and carry their exit code (UsageError 2, RunFailure 1).
KNOWN_ERRORS: dict[type[Exception], int] = {
    ScenarioError: EXIT_USAGE,  # a bad scenario or world file, variant or override
    AgentConfigError: EXIT_USAGE,  # a bad agent config file
    # A path the user named is missing, already there, the wrong kind or not accessible.
    FileNotFoundError: EXIT_USAGE,
    FileExistsError: EXIT_USAGE,
    IsADirectoryError: EXIT_USAGE,
    NotADirectoryError: EXIT_USAGE,
    PermissionError: EXIT_USAGE,
    OSError: EXIT_FAILURE,  # the machine failed the run: disk full, I/O error, port taken
    LaunchError: EXIT_FAILURE,  # an agent died or did not start, the run stalled
    TransportError: EXIT_FAILURE,  # a Zenoh session could not open (port taken, bad endpoint)
    ConductorError: EXIT_FAILURE,
    # Runtime state the run found: another run's journal, one in use, a tail it could not set
    # aside. Even an identity mismatch is not a configuration mistake: the config may be right
    # and the journal a leftover, and the fix (move it, stop the other agent) is operational.
    JournalError: EXIT_FAILURE,
    # A message that broke the protocol reached the command instead of being counted and
    # dropped (RemoteProtocolError) or refused before sending (LocalProtocolError).
    ProtocolError: EXIT_FAILURE,
}


def exit_code(exc: Exception) -> int | None:
    """The exit code of a known error, None for anything else (a bug: keep its traceback)."""
    if isinstance(exc, CommandError):
        return exc.exit_code
    return next((KNOWN_ERRORS[c] for c in type(exc).__mro__ if c in KNOWN_ERRORS), None)


class Parser(argparse.ArgumentParser):
    """argparse's own mistakes (unknown option, bad value, missing argument) as one line, like
    the project's: ``semfleet COMMAND: error: … (semfleet COMMAND --help)``, exit code 2.
    Sub-command parsers are made of the same class."""

    def error(self, message: str) -> NoReturn:
        print(
            f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)",
            file=sys.stderr,
        )
        sys.exit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="semfleet",
        description="Distributed, consistent, multi-robot semantic SLAM.",
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging (semfleet's own modules)"
    )
    parser.add_argument("--version", action="version", version=f"semfleet {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    scenario.add_parser(sub)
    classifier.add_parser(sub)
    study.add_parser(sub)
    dataset.add_parser(sub)
    export_command.add_parser(sub)
    demo.add_parser(sub)
    ufastslam.add_parser(sub)
    launch_command.add_parser(sub)
    agent.add_parser(sub)
    fleet.add_parser(sub)
    replay.add_parser(sub)
    router.add_parser(sub)
    return parser


OWN_LOGGERS = ("semfleet", "agents", "deploy", "estimator", "protocol", "sim")


def _version() -> str:
    try:
        return importlib.metadata.version("semfleet")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed)"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    if args.verbose:  # our debug lines only, not matplotlib's, numba's or asyncio's
        for package in OWN_LOGGERS:
            logging.getLogger(package).setLevel(logging.DEBUG)
    console = make_console()
    previous = _raise_on_stop_signals()
    try:
        code: int = args.run(args, console)
        return code
    except KeyboardInterrupt:
        _error("interrupted")
        return EXIT_INTERRUPTED
    except SignalExit as stop:
        _error(f"stopped by {signal.Signals(stop.signal_number).name}")
        return stop.exit_code
    except Exception as exc:
        known = exit_code(exc)
        if known is None:
            raise
        _error(_message(exc))
        return known
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _raise_on_stop_signals() -> dict[signal.Signals, Any]:
    """SIGTERM and SIGHUP raise :class:`SignalExit` in the main thread (commands that run an
    event loop install their own handlers while it runs); the previous handlers, to restore."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def raise_exit(signum: int, _frame: object) -> None:
        raise SignalExit(signum)

    return {sig: signal.signal(sig, raise_exit) for sig in (signal.SIGTERM, signal.SIGHUP)}


def _message(exc: Exception) -> str:
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror}"  # not "[Errno 2] No such file...: 'x'"
    return str(exc) or type(exc).__name__


def _error(message: str) -> None:
    """One plain line on stderr: never wrapped, whatever the terminal width."""
    print(f"semfleet: error: {' '.join(message.split())}", file=sys.stderr)


def entry() -> NoReturn:
    """The ``semfleet`` command: :func:`main`, then the exit. A process that opened a Zenoh
    session leaves at once (``os._exit``) with its output flushed, as ``semfleet agent`` does:
    tearing the interpreter down while Zenoh's threads still run can abort it after the command
    did its work (a Zenoh thread that calls into Python during finalisation is unwound through
    Rust frames: "FATAL: exception not rethrown", SIGABRT; seen once in CI after a replay)."""
    code = main()
    zenoh_transport = sys.modules.get("agents.transport.zenoh_transport")
    if zenoh_transport is not None and zenoh_transport.ZenohTransport.sessions_opened:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
