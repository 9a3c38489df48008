"""The errors a ``semfleet`` command reports as one line, and the exit codes it reports them with.

A command raises :class:`UsageError` for a mistake the user can fix in what they typed or wrote
(an argument, a config, scenario or log file) and :class:`RunFailure` when a correct command
failed while running (an agent died, a worker process was killed). :func:`deploy.cli.main.main`
prints either as one line and exits with its ``exit_code``; it maps the project's other error types
(scenario, journal, protocol...) with a table of its own, and lets every other exception — a bug —
keep its traceback.
"""

from __future__ import annotations

from typing import ClassVar

EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class CommandError(Exception):
    """A failure a command reports as one sentence; ``exit_code`` says whose it is."""

    exit_code: ClassVar[int] = EXIT_FAILURE


class UsageError(CommandError):
    """Bad arguments or a bad configuration, scenario or input file (exit 2)."""

    exit_code = EXIT_USAGE


class RunFailure(CommandError):
    """The command was right but the run failed (exit 1)."""

    exit_code = EXIT_FAILURE


class SignalExit(BaseException):
    """SIGTERM or SIGHUP arrived while a command ran outside an event loop (a study, a scenario
    command): raised in the main thread like ``KeyboardInterrupt`` for Ctrl-C, so that every
    ``with`` and ``finally`` on the way out runs (worker processes are stopped, files closed).
    Not an ``Exception``: no ``except Exception`` on the way may swallow it."""

    def __init__(self, signal_number: int) -> None:
        super().__init__(signal_number)
        self.signal_number = signal_number
        self.exit_code = 128 + signal_number
