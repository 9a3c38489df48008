"""The agent processes of a launch: ports, config files, start, kill, and a shutdown that leaves
nothing behind.

Agents are started with ``subprocess`` (never a fork of a process with an open Zenoh session) in
the launcher's process group, so a terminal's Ctrl-C reaches all of them. Three lines of defence
make sure no agent outlives its launcher:

1. :class:`SignalStop` turns SIGTERM, SIGHUP and SIGINT into a cancellation of the run, whose
   ``finally`` stops every agent (``ctl/stop``, then SIGTERM, then SIGKILL after
   :data:`SHUTDOWN_GRACE_S`) before the launcher exits with the signal's code.
2. An agent that dies unplanned ends the run (:meth:`Supervisor.check`), through the same
   ``finally``.
3. Every agent gets a parent-death signal (Linux ``PR_SET_PDEATHSIG``): when the launcher dies
   without cleaning up — SIGKILL, a crash — the kernel sends each agent SIGTERM, which it handles
   like any stop (journal closed, exit 0).
"""

from __future__ import annotations

import asyncio
import ctypes
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar

import tomli_w

from deploy.base.errors import CommandError
from deploy.launch.errors import LaunchError

SHUTDOWN_GRACE_S = 2.0
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


class Stopped(CommandError):
    """A signal stopped the launch; every agent was stopped before this was raised. The exit code
    is the shell's for a death by that signal (128 + its number)."""

    signal_number: ClassVar[int] = 0

    def __init__(self) -> None:
        name = signal.Signals(self.signal_number).name
        super().__init__(f"stopped by {name}; every agent was stopped")


class Terminated(Stopped):
    signal_number = signal.SIGTERM
    exit_code = 128 + signal.SIGTERM


class HungUp(Stopped):
    signal_number = signal.SIGHUP
    exit_code = 128 + signal.SIGHUP


def free_ports(n: int) -> list[int]:
    """``n`` distinct free TCP ports on 127.0.0.1 (held open together while choosing)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def write_agent_config(
    path: Path,
    agent: Mapping[str, Any],
    zenoh: Mapping[str, Any],
    security: Mapping[str, Any] | None = None,
    ros2: Mapping[str, Any] | None = None,
) -> None:
    """An agent config file (docs/agents.md): ``[agent]``, ``[zenoh]`` and, given, ``[security]``
    and ``[ros2]`` (docs/ros2.md); None values left out."""
    doc = {
        "agent": {k: v for k, v in agent.items() if v is not None},
        "zenoh": {k: v for k, v in zenoh.items() if v is not None},
    }
    if security is not None:
        doc["security"] = dict(security)
    if ros2 is not None:
        doc["ros2"] = dict(ros2)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Whole or not at all: an agent started elsewhere may read it while the launch goes on.
    part = path.with_name(f".{path.name}.part")
    part.write_text(tomli_w.dumps(doc), encoding="utf-8")
    part.replace(path)


def _prctl() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    return prctl


_PRCTL = _prctl()


def _die_with(parent: int) -> Callable[[], None]:
    """The agent's ``preexec_fn``: SIGTERM when the thread that started it dies. The kernel ties
    the signal to that *thread*, so agents are started on the event loop's thread, which lives as
    long as the launcher. Between fork and exec, with Zenoh's threads in the parent, it calls
    nothing but the ``prctl`` looked up beforehand and ``getppid``: no lock another thread could
    have held at the fork."""
    term = int(signal.SIGTERM)

    def preexec() -> None:
        if _PRCTL is not None:
            _PRCTL(_PR_SET_PDEATHSIG, term, 0, 0, 0)
        if os.getppid() != parent:  # the launcher died before the signal was armed
            os._exit(1)

    return preexec


@dataclass(slots=True)
class AgentProcess:
    robot: str
    config: Path
    log: Path
    port: int
    proc: subprocess.Popen[bytes] | None = None
    expected_exit: bool = False
    starts: int = 0
    # A command the agent runs under, e.g. ``ip netns exec NS``: one that execs the agent in
    # place (same pid, so signals and the parent-death signal still reach the agent itself).
    prefix: tuple[str, ...] = ()

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


class Supervisor:
    """Starts, kills, watches and stops the agent processes of one launch; ``events`` records
    what a reader of the run should know (kills, restarts, an agent that ignored SIGTERM)."""

    def __init__(self) -> None:
        self.agents: dict[str, AgentProcess] = {}
        self.events: list[str] = []

    def add(self, agent: AgentProcess) -> None:
        self.agents[agent.robot] = agent

    def start(self, robot: str) -> None:
        """Start ``robot``'s agent; its output goes to its log (appended across restarts)."""
        a = self.agents[robot]
        if a.running():  # a second agent of one robot would find the journal taken and exit
            raise LaunchError(f"agent {robot} is already running (pid {a.proc.pid})")  # type: ignore[union-attr]
        a.log.parent.mkdir(parents=True, exist_ok=True)
        cmd = [*a.prefix, sys.executable, "-m", "deploy.cli", "agent", "--robot", robot]
        cmd += ["--config", str(a.config.absolute())]  # whoever looks knows which run it is
        with open(a.log, "ab") as log:
            a.proc = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, preexec_fn=_die_with(os.getpid())
            )
        a.expected_exit = False
        a.starts += 1

    def kill(self, robot: str) -> None:
        a = self.agents[robot]
        if a.running():
            assert a.proc is not None
            a.expected_exit = True
            a.proc.send_signal(signal.SIGKILL)
            a.proc.wait()

    def check(self) -> None:
        """Raise if an agent died without being told to."""
        for a in self.agents.values():
            if a.proc is not None and not a.expected_exit and a.proc.poll() is not None:
                raise LaunchError(
                    f"agent {a.robot} exited unexpectedly with code {a.proc.returncode} "
                    f"(log {a.log}): {_tail(a.log)}"
                )

    def stop_all(self) -> None:
        """SIGTERM to every running agent, SIGKILL to those still running after
        :data:`SHUTDOWN_GRACE_S`; returns once every agent has exited."""
        procs = [a for a in self.agents.values() if a.running()]
        for a in procs:
            a.expected_exit = True
            a.proc.send_signal(signal.SIGTERM)  # type: ignore[union-attr]
        deadline = time.monotonic() + SHUTDOWN_GRACE_S
        for a in procs:
            assert a.proc is not None
            try:
                a.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.events.append(f"{a.robot} ignored SIGTERM for {SHUTDOWN_GRACE_S} s: killed")
                a.proc.kill()
                a.proc.wait()


def _tail(path: Path, lines: int = 3) -> str:
    """The last ``lines`` of an agent's log, each JSON record as its message only: the error
    line stays a line (a counters record alone is 1.4 kB)."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    except OSError:
        return "(no log)"
    return " | ".join(_message(line) for line in text[-lines:]) or "(empty log)"


def _message(line: str) -> str:
    try:
        record = json.loads(line)
    except ValueError:
        return line  # a traceback's line, or the command's own one-line error
    message = record.get("msg") if isinstance(record, dict) else None
    return message if isinstance(message, str) else line


class SignalStop:
    """While entered (in a task on the main thread): SIGTERM, SIGHUP or SIGINT cancel that task.
    After :meth:`hold` — the task's cleanup has begun — a signal is only recorded, so a second
    Ctrl-C cannot cut the cleanup short. :meth:`raise_if_stopped` then raises what the first
    signal means: :class:`Terminated`, :class:`HungUp`, or ``KeyboardInterrupt`` for SIGINT.
    Elsewhere than the main thread no handler can be installed and the signals keep their
    default meaning.

    The cancellation is repeated every :data:`RECANCEL_S` until the cleanup begins: Python
    3.11's ``asyncio.wait_for`` drops a cancellation that lands as its awaited future completes,
    and the conductor waits that way all the time (measured: one signal in a few was ignored and
    the run went on to its end)."""

    RECANCEL_S = 0.1

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self._holding = False
        self._task: asyncio.Task[Any] | None = None
        self._installed: list[signal.Signals] = []

    def __enter__(self) -> SignalStop:
        loop = asyncio.get_running_loop()
        self._task = asyncio.current_task()
        for sig in STOP_SIGNALS:
            try:
                loop.add_signal_handler(sig, self.on_signal, sig)
            except (ValueError, RuntimeError):  # not the main thread
                continue
            self._installed.append(sig)
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _tb: TracebackType | None,
    ) -> None:
        loop = asyncio.get_running_loop()
        for sig in self._installed:
            loop.remove_signal_handler(sig)

    def on_signal(self, sig: signal.Signals) -> None:
        """What a stop signal does (installed as its handler)."""
        if self.received is None:
            self.received = sig
            self._cancel()

    def _cancel(self) -> None:
        task = self._task
        if self._holding or task is None or task.done():
            return
        task.cancel()
        asyncio.get_running_loop().call_later(self.RECANCEL_S, self._cancel)

    def hold(self) -> None:
        self._holding = True

    def raise_if_stopped(self) -> None:
        if self.received == signal.SIGINT:
            raise KeyboardInterrupt
        if self.received == signal.SIGTERM:
            raise Terminated
        if self.received == signal.SIGHUP:
            raise HungUp
