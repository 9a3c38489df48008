"""`semfleet fleet status|watch|stop`: an operator's view of a running fleet, from outside it.

The operator opens its own Zenoh session that only dials out (``--connect``, never listens). By
default it is a Zenoh *client*: the robot it reaches routes for it, so it sees that robot and every
robot linked to it, whatever the fleet's gossip settings (peers never forward for each other, but
they do for their clients). ``--mode peer`` joins as a peer instead: with gossip scouting on it
links directly to every robot the fleet's own gossip reveals, and sees only the robots it dialled
when the fleet runs without gossip.

It uses three keys of docs/agents.md: the liveliness tokens ``alive/<robot>``, the estimates
``estimate/<robot>`` (published after every step and at once on ``ctl/status``), and the
``ctl/status`` and ``ctl/stop`` it sends. :class:`FleetView` is the sans-I/O part (liveliness
changes and estimate bytes with ``now`` in; tables, documents and a map are drawn from it),
:class:`StopProgress` the timing of a stop; the asyncio shells around them only open the session,
pump messages in, send what they are told and wait.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import re
import signal
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.live import Live
from rich.table import Table

from agents.control import Status, Stop, encode_control
from agents.transport.base import Inbox, Keys, Message
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.errors import RunFailure, UsageError
from estimator.hybrid import BeliefSnapshot
from estimator.metrics import world_position_cov
from estimator.models import ROBOT_ID_RULE
from estimator.pruning import class_marginals
from protocol.errors import RemoteProtocolError
from protocol.estimate import EstimateLimits, EstimateMessage, decode_estimate
from protocol.validate import valid_id

Array = NDArray[np.float64]

MODES = ("client", "peer")
RESULTS_FORMAT = 1
# Liveliness history and the first answers to ctl/status arrive within milliseconds on loopback;
# a status waits at least this long for robots reached through another robot to show up.
SETTLE_S = 0.5
# ctl/status and ctl/stop are re-sent this often to robots that have not reacted (lost puts,
# robots that appeared late).
RESEND_S = 0.5
# A stop is confirmed once no token has been alive for this long: a client whose router robot
# stopped fails over to its next --connect endpoint and sees the remaining tokens again (within
# 0.1 s on loopback, measured).
STOP_CONFIRM_S = 1.0
# Shown when present in any robot's counters; --json and estimates.json carry every counter.
COUNTER_COLUMNS = (
    ("stacks_sent", "sent"),
    ("stacks_merged", "merged"),
    ("stacks_invalid", "invalid"),
    ("slots_rejected", "slots rej."),
    ("frames_processed", "frames"),
    ("frames_quarantined", "quarantined"),
)
_IP_PROTOCOLS = {"tcp", "udp", "tls", "quic", "ws"}
_OTHER_PROTOCOLS = {"unixsock-stream", "unixpipe", "serial", "vsock"}
_ENDPOINT = re.compile(r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<address>[^?#]+)(?P<rest>[?#].*)?$")


# --------------------------------------------------------------------------- arguments


def endpoint(text: str) -> str:
    """A Zenoh endpoint ``PROTOCOL/ADDRESS`` (e.g. ``tcp/127.0.0.1:7447``); IP protocols need a
    ``host:port`` with a port in 1..65535."""
    m = _ENDPOINT.fullmatch(text)
    if m is None or m["proto"] not in _IP_PROTOCOLS | _OTHER_PROTOCOLS:
        known = ", ".join(sorted(_IP_PROTOCOLS | _OTHER_PROTOCOLS))
        raise UsageError(
            f"--connect {text!r}: expected PROTOCOL/ADDRESS such as tcp/127.0.0.1:7447 "
            f"(protocols: {known})"
        )
    if m["proto"] in _IP_PROTOCOLS:
        host, colon, port = m["address"].rpartition(":")
        if not (colon and host and port.isdigit() and 1 <= int(port) <= 65535):
            raise UsageError(
                f"--connect {text!r}: expected HOST:PORT with a port in 1..65535 after "
                f"{m['proto']}/"
            )
    return text


def connection(args: argparse.Namespace) -> tuple[ZenohSettings, Keys]:
    """The session settings and the fleet's keys from the common options."""
    if not valid_id(args.fleet):
        raise UsageError(f"--fleet {args.fleet!r}: {ROBOT_ID_RULE}")
    endpoints = tuple(endpoint(e) for e in args.connect)
    config_file = None
    if args.zenoh_config is not None:
        config_file = Path(args.zenoh_config)
        if not config_file.is_file():
            raise UsageError(f"--zenoh-config {config_file}: no such file")
    if not (math.isfinite(args.timeout) and 0 < args.timeout <= 3600):
        raise UsageError(f"--timeout {args.timeout}: must be in (0, 3600] s")
    return session_settings(endpoints, args.mode, config_file), Keys(args.fleet)


def session_settings(
    endpoints: tuple[str, ...], mode: str = "client", config_file: Path | None = None
) -> ZenohSettings:
    """An operator's session: dials ``endpoints``, never listens; ``mode`` "client" or "peer"
    (with gossip scouting)."""
    extra = {"mode": mode} if mode != "peer" else {}
    return ZenohSettings(connect=endpoints, gossip=True, config_file=config_file, extra=extra)


# --------------------------------------------------------------------------- the view


@dataclass(slots=True)
class RobotState:
    """What the operator knows of one robot: its token, its latest estimate (``received``: the
    ``now`` it arrived) and the trail of its estimated positions, one (k, x, y) per new step."""

    alive: bool = False
    estimate: EstimateMessage | None = None
    received: float = math.nan
    trail: list[tuple[int, float, float]] = field(default_factory=list)


class FleetView:
    """Liveliness changes and estimates of one fleet in, the operator's picture out. No I/O, no
    clock: every event comes with ``now``."""

    def __init__(self, keys: Keys, limits: EstimateLimits | None = None) -> None:
        self.keys = keys
        self.limits = limits or EstimateLimits()
        self.robots: dict[str, RobotState] = {}
        self.invalid = 0
        self.last_error = ""

    def on_message(self, m: Message, now: float) -> bool:
        """Apply one delivery (a liveliness change or an estimate put); True if anything
        changed."""
        robot = self.keys.robot_of(m.key)
        if m.kind in ("alive", "gone"):
            if robot is None or m.key != self.keys.alive(robot):
                return False
            state = self.robots.setdefault(robot, RobotState())
            before, state.alive = state.alive, m.kind == "alive"
            return before != state.alive
        if robot is None or m.key != self.keys.estimate(robot):
            return False
        try:
            est = decode_estimate(m.payload, self.limits)
        except RemoteProtocolError as exc:
            self.invalid += 1
            self.last_error = f"{robot}: {exc}"
            return False
        if est.robot != robot:
            self.invalid += 1
            self.last_error = f"{robot}: estimate signed {est.robot!r} on its key"
            return False
        state = self.robots.setdefault(robot, RobotState())
        if state.estimate is not None and est.k < state.estimate.k:
            return False  # an older step overtaken on the way
        state.estimate, state.received = est, now
        if not state.trail or est.k > state.trail[-1][0]:
            pose, _ = mixture_moments(*_robot_arrays(primary_belief(est)))
            state.trail.append((est.k, float(pose[0]), float(pose[1])))
        return True

    def answered(self) -> list[str]:
        return sorted(r for r, s in self.robots.items() if s.estimate is not None)

    def alive(self) -> list[str]:
        return sorted(r for r, s in self.robots.items() if s.alive)

    def unanswered(self) -> list[str]:
        """Alive robots with no estimate yet."""
        return sorted(r for r, s in self.robots.items() if s.alive and s.estimate is None)


def primary_belief(est: EstimateMessage) -> BeliefSnapshot:
    """The belief that stands for the robot: D (``distributed``) if published, else the first."""
    return est.beliefs.get("distributed") or est.beliefs[sorted(est.beliefs)[0]]


def _robot_arrays(snap: BeliefSnapshot) -> tuple[Array, Array, Array]:
    return snap.weights, snap.robot_pose, snap.robot_cov


def mixture_moments(weights: Array, poses: Array, covs: Array) -> tuple[Array, Array]:
    """Weighted mean pose (..., 3) and moment-matched world position covariance (..., 2, 2) of
    the hypotheses' Gaussians: weights (H,), poses (H, ..., 3), covs (H, ..., 3, 3).

    x, y are the weighted means; θ is the weighted circular mean. The covariance is
    Σ_h w_h [R Σ^h_xy Rᵀ + (t^h − μ)(t^h − μ)ᵀ] (within plus between hypotheses).
    """
    w = weights.reshape((-1,) + (1,) * (poses.ndim - 1))
    xy = np.sum(w * poses[..., :2], axis=0)
    theta = np.arctan2(
        np.sum(w[..., 0] * np.sin(poses[..., 2]), axis=0),
        np.sum(w[..., 0] * np.cos(poses[..., 2]), axis=0),
    )
    spread = poses[..., :2] - xy
    within = world_position_cov(poses, covs)
    between = spread[..., :, None] * spread[..., None, :]
    cov = np.sum(w[..., None] * (within + between), axis=0)
    return np.concatenate([xy, theta[..., None]], axis=-1), cov


# --------------------------------------------------------------------------- documents


def belief_doc(snap: BeliefSnapshot, num_classes: int) -> dict[str, Any]:
    """One belief for estimates.json (docs/results.md, "Fleet estimates")."""
    top = int(np.argmax(snap.weights))
    robot_pose, robot_cov = mixture_moments(snap.weights, snap.robot_pose, snap.robot_cov)
    obj_pose, obj_cov = mixture_moments(snap.weights, snap.object_pose, snap.object_cov)
    marginals = class_marginals(snap.weights, snap.classes, num_classes)
    objects = [
        {
            "id": int(j),
            "map_class": int(snap.classes[top, i]),
            "marginals": marginals[i].tolist(),
            "pose": obj_pose[i].tolist(),
            "cov_xy": obj_cov[i].tolist(),
        }
        for i, j in enumerate(snap.object_ids)
    ]
    return {
        "hypotheses": len(snap.weights),
        "map_weight": float(snap.weights[top]),
        "robot_pose": robot_pose.tolist(),
        "robot_cov_xy": robot_cov.tolist(),
        "objects": objects,
    }


def classes_seen(view: FleetView) -> int:
    """1 + the largest class index any hypothesis holds (estimates do not carry M; a class no
    hypothesis holds has probability 0)."""
    top = 0
    for state in view.robots.values():
        if state.estimate is not None:
            for snap in state.estimate.beliefs.values():
                if snap.classes.size:
                    top = max(top, int(snap.classes.max()) + 1)
    return max(top, 1)


def estimates_doc(view: FleetView, watched_s: float) -> dict[str, Any]:
    """The document of estimates.json: every robot's latest estimate and its trail."""
    m = classes_seen(view)
    robots: dict[str, Any] = {}
    for robot in view.answered():
        state = view.robots[robot]
        est = state.estimate
        assert est is not None
        robots[robot] = {
            "k": est.k,
            "alive": state.alive,
            "counters": dict(sorted(est.counters.items())),
            "beliefs": {name: belief_doc(est.beliefs[name], m) for name in sorted(est.beliefs)},
            "trail": [list(p) for p in state.trail],
        }
    return {
        "format": RESULTS_FORMAT,
        "fleet": view.keys.fleet,
        "watched_s": round(watched_s, 3),
        "classes_seen": m,
        "robots": robots,
    }


def status_doc(view: FleetView, elapsed_s: float, answered_s: float) -> dict[str, Any]:
    """``fleet status --json``: per robot its token, step, hypotheses, objects and counters."""
    robots = []
    for robot in sorted(view.robots):
        state = view.robots[robot]
        est = state.estimate
        beliefs = sorted(est.beliefs) if est is not None else []
        robots.append(
            {
                "robot": robot,
                "alive": state.alive,
                "k": est.k if est is not None else None,
                "hypotheses": {b: len(est.beliefs[b].weights) for b in beliefs} if est else {},
                "objects": {b: len(est.beliefs[b].object_ids) for b in beliefs} if est else {},
                "counters": dict(sorted(est.counters.items())) if est is not None else {},
            }
        )
    return {
        "fleet": view.keys.fleet,
        "elapsed_s": round(elapsed_s, 3),
        "answered_s": round(answered_s, 3) if math.isfinite(answered_s) else None,
        "invalid_estimates": view.invalid,
        "robots": robots,
    }


def fleet_table(view: FleetView, title: str, now: float | None = None) -> Table:
    """Robot, token, step, hypotheses and objects of D / L, the :data:`COUNTER_COLUMNS` some
    robot reports and, given ``now``, the age of the latest estimate."""
    estimates = [s.estimate for s in view.robots.values() if s.estimate is not None]
    shown = [(k, h) for k, h in COUNTER_COLUMNS if any(k in e.counters for e in estimates)]
    t = Table(title=title)
    for name in ("robot", "alive", "step", "hyp. D/L", "objects D/L"):
        t.add_column(name, justify="left" if name == "robot" else "right")
    for _, heading in shown:
        t.add_column(heading, justify="right")
    if now is not None:
        t.add_column("age (s)", justify="right")
    for robot in sorted(view.robots):
        state = view.robots[robot]
        est = state.estimate
        alive = "[green]yes[/]" if state.alive else "[red]no[/]"
        ages = ["—"] if now is not None else []
        if est is None:
            t.add_row(robot, alive, "—", "—", "—", *("—" for _ in shown), *ages)
            continue
        d, loc = est.beliefs.get("distributed"), est.beliefs.get("local")
        hyp = "/".join(str(len(s.weights)) if s else "—" for s in (d, loc))
        objects = "/".join(str(len(s.object_ids)) if s else "—" for s in (d, loc))
        counters = (str(est.counters.get(k, "—")) for k, _ in shown)
        if now is not None:
            ages = [f"{now - state.received:.1f}"]
        t.add_row(robot, alive, str(est.k), hyp, objects, *counters, *ages)
    return t


# --------------------------------------------------------------------------- the map


def plot_robot_map(
    ax: Any, robot: str, doc: Mapping[str, Any], belief: str, colours: Mapping[str, Any]
) -> None:
    """One robot's ``belief`` from an estimates.json document: objects coloured by their most
    probable class with 2σ ellipses, every robot's trail and latest position (its own belief)."""
    import matplotlib.pyplot as plt

    from deploy.plots import covariance_ellipse

    class_colours = plt.get_cmap("Set1")
    entry = doc["robots"][robot]
    b = entry["beliefs"][belief]
    drawn: set[int] = set()
    for obj in b["objects"]:
        c = int(np.argmax(obj["marginals"]))
        colour = class_colours(c % 9)
        xy = np.array(obj["pose"][:2])
        covariance_ellipse(ax, xy, np.array(obj["cov_xy"]), color=colour, lw=0.8)
        label = f"class {c + 1}" if c not in drawn else None
        drawn.add(c)
        ax.plot(*xy, "s", color=colour, ms=5, label=label)
        ax.annotate(str(obj["id"]), xy, textcoords="offset points", xytext=(4, 4), fontsize=7)
    for other, e in doc["robots"].items():
        colour = colours[other]
        trail = np.array(e["trail"], dtype=float).reshape(-1, 3)
        ax.plot(trail[:, 1], trail[:, 2], "-", color=colour, lw=1.5 if other == robot else 0.8)
        own = e["beliefs"][_main_name(e)]
        x, y, theta = own["robot_pose"]
        if other == robot:
            covariance_ellipse(ax, np.array([x, y]), np.array(own["robot_cov_xy"]), color=colour)
        marker = (3, 0, math.degrees(theta) - 90)  # a triangle pointing along θ
        ax.plot(x, y, marker=marker, color=colour, ms=10 if other == robot else 6, ls="none")
        ax.annotate(other, (x, y), textcoords="offset points", xytext=(6, -10), color=colour)
    ax.set_aspect("equal")
    ax.set_title(f"{robot} at k = {entry['k']}: {belief}, {b['hypotheses']} hypotheses (2σ)")
    ax.grid(True, alpha=0.3)
    if drawn:
        ax.legend(fontsize=7, loc="best")


def _main_name(entry: Mapping[str, Any]) -> str:
    beliefs = entry["beliefs"]
    return "distributed" if "distributed" in beliefs else sorted(beliefs)[0]


def write_map(path: Path, doc: Mapping[str, Any]) -> None:
    """map.png: one panel per robot (its D, or its only belief), on common axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    robots = sorted(doc["robots"])
    colours = {r: plt.get_cmap("tab10")(i % 10) for i, r in enumerate(robots)}
    cols = min(3, len(robots))
    rows = math.ceil(len(robots) / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(6 * cols, 6 * rows), squeeze=False, sharex=True, sharey=True
    )
    for ax, robot in zip(axes.flat, robots, strict=False):
        plot_robot_map(ax, robot, doc, _main_name(doc["robots"][robot]), colours)
    for ax in list(axes.flat)[len(robots) :]:
        ax.set_visible(False)
    fig.suptitle(f"fleet {doc['fleet']}: estimates after {doc['watched_s']:.0f} s of watch")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def write_watch_results(out: Path, view: FleetView, watched_s: float) -> list[Path]:
    """estimates.json and map.png in ``out`` (created)."""
    out.mkdir(parents=True, exist_ok=True)
    doc = estimates_doc(view, watched_s)
    path = out / "estimates.json"
    path.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    map_path = out / "map.png"
    write_map(map_path, doc)
    return [path, map_path]


# --------------------------------------------------------------------------- sessions


class Session:
    """The operator's Zenoh session: the fleet's tokens and estimates flow into a
    :class:`FleetView`."""

    def __init__(
        self, settings: ZenohSettings, keys: Keys, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.keys = keys
        self.clock = clock
        self.view = FleetView(keys)
        self.transport = ZenohTransport(settings)
        self.endpoints = ", ".join(settings.connect)
        self.inbox = Inbox(100_000)

    async def __aenter__(self) -> Session:
        self.transport.watch_alive(self.keys.alive("*"), self.inbox)
        self.transport.subscribe(self.keys.estimate("*"), self.inbox)
        try:
            await self.transport.open()
        except Exception as exc:  # zenoh.ZError, which only the transport module may name
            first = str(exc).split(" at /", 1)[0].strip()
            raise RunFailure(f"cannot reach {self.endpoints}: {first}") from None
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.transport.close()

    def send(self, message: Status | Stop, name: str) -> None:
        self.transport.publish(self.keys.ctl(name), encode_control(message))

    async def pump(self, timeout: float) -> bool:
        """Wait up to ``timeout`` for deliveries and feed them to the view; True if it changed."""
        await self.inbox.wait(max(0.0, timeout))
        now = self.clock()
        changed = False
        for m in self.inbox.drain():
            changed |= self.view.on_message(m, now)
        return changed

    def nobody(self, waited: float) -> RunFailure:
        return RunFailure(
            f"no robot of fleet {self.keys.fleet!r} answered within {waited:g} s "
            f"at {self.endpoints}"
        )


async def collect_status(
    settings: ZenohSettings, keys: Keys, timeout: float
) -> tuple[FleetView, float, float]:
    """Ask for every robot's estimate; return the view once every robot whose token showed up
    answered (after at least :data:`SETTLE_S`), or at ``timeout``; with the seconds it took and
    the seconds from the request to the last answer (NaN without one)."""
    async with Session(settings, keys) as s:
        start = s.clock()
        s.send(Status(), "status")
        asked = start
        while (now := s.clock()) < start + timeout:
            settled = now >= start + min(SETTLE_S, timeout)
            if settled and s.view.answered() and not s.view.unanswered():
                break
            if s.view.unanswered() and now - asked >= RESEND_S:
                s.send(Status(), "status")
                asked = now
            await s.pump(min(0.05, start + timeout - now))
        elapsed = s.clock() - start
        if not s.view.robots:
            raise s.nobody(timeout)
        received = [st.received for st in s.view.robots.values() if st.estimate is not None]
        return s.view, elapsed, max(received, default=math.nan) - start


async def watch_fleet(
    settings: ZenohSettings,
    keys: Keys,
    duration: float | None,
    timeout: float,
    on_change: Callable[[FleetView, float], None],
) -> tuple[FleetView, float]:
    """Follow the fleet until ``duration`` s, SIGINT or SIGTERM; ``on_change(view, now)`` on
    every change and at least once a second. Robots that show up without an estimate are asked
    for one (``ctl/status``, at most every :data:`RESEND_S`). No robot within ``timeout`` s is an
    :class:`~deploy.errors.RunFailure`."""
    ended = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, ended.set)
    try:
        async with Session(settings, keys) as s:
            start = s.clock()
            s.send(Status(), "status")
            asked = shown = start
            end = math.inf if duration is None else start + duration
            while not ended.is_set() and (now := s.clock()) < end:
                if not s.view.robots and now >= start + timeout:
                    raise s.nobody(timeout)
                if s.view.unanswered() and now - asked >= RESEND_S:
                    s.send(Status(), "status")
                    asked = now
                changed = await s.pump(min(0.25, end - now))
                if changed or s.clock() - shown >= 1.0:
                    shown = s.clock()
                    on_change(s.view, shown)
            return s.view, s.clock() - start
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


@dataclass(slots=True)
class StopProgress:
    """The timing of a stop, from whether any token is alive and ``now``: ``ctl/stop`` again
    every :data:`RESEND_S` while some token is alive; over once none has been for
    :data:`STOP_CONFIRM_S`, because a client whose robot just left fails over to its next
    endpoint and may see the others' tokens again."""

    sent: float
    last_sent: float = math.nan
    quiet_since: float | None = None

    def __post_init__(self) -> None:
        if math.isnan(self.last_sent):
            self.last_sent = self.sent

    def step(self, anyone_alive: bool, now: float) -> Literal["resend", "wait", "done"]:
        if anyone_alive:
            self.quiet_since = None
            if now - self.last_sent >= RESEND_S:
                self.last_sent = now
                return "resend"
            return "wait"
        if self.quiet_since is None:
            self.quiet_since = now
        return "done" if now - self.quiet_since >= STOP_CONFIRM_S else "wait"


async def stop_fleet(
    settings: ZenohSettings, keys: Keys, reason: str, timeout: float
) -> tuple[list[str], list[str], float]:
    """Publish ``ctl/stop`` and follow the tokens (:class:`StopProgress`) until the stop is over
    or ``timeout``; (stopped, still alive, seconds from the stop to the last token gone)."""
    async with Session(settings, keys) as s:
        start = s.clock()
        while s.clock() < start + min(SETTLE_S, timeout):
            await s.pump(0.05)
        seen = s.view.alive()
        if not seen:
            raise s.nobody(min(SETTLE_S, timeout))
        progress = StopProgress(s.clock())
        s.send(Stop(reason), "stop")
        while (now := s.clock()) < progress.sent + timeout:
            action = progress.step(bool(s.view.alive()), now)
            if action == "done":
                break
            if action == "resend":
                s.send(Stop(reason), "stop")
            await s.pump(0.05)
        seen = sorted(set(seen) | set(s.view.robots))
        still = s.view.alive()
        stopped = [r for r in seen if r not in still]
        return stopped, still, (progress.quiet_since or s.clock()) - progress.sent


# --------------------------------------------------------------------------- commands


def run_status(args: argparse.Namespace, console: Console) -> int:
    settings, keys = connection(args)
    view, elapsed, answered = asyncio.run(collect_status(settings, keys, args.timeout))
    if args.json:
        print(json.dumps(status_doc(view, elapsed, answered), indent=1))
        return 0
    title = f"fleet {keys.fleet} at {', '.join(settings.connect)}"
    console.print(fleet_table(view, title))
    console.print(
        f"{len(view.alive())} alive, {len(view.answered())} answered"
        + (f" (the last {answered:.3f} s after ctl/status)" if math.isfinite(answered) else "")
        + (f"; {view.invalid} invalid estimates ({view.last_error})" if view.invalid else "")
    )
    return 0


def run_watch(args: argparse.Namespace, console: Console) -> int:
    settings, keys = connection(args)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration {args.duration}: must be a positive number")
    title = f"fleet {keys.fleet} at {', '.join(settings.connect)}"
    with Live(console=console, refresh_per_second=4, transient=False) as live:

        def show(view: FleetView, now: float) -> None:
            live.update(fleet_table(view, title, now))

        view, watched = asyncio.run(watch_fleet(settings, keys, args.duration, args.timeout, show))
    if not console.is_terminal:
        console.line()  # Live leaves its last frame without a newline outside a terminal
    if not view.answered():
        raise RunFailure(
            f"no robot of fleet {keys.fleet!r} sent an estimate during the watch ({watched:.1f} s)"
        )
    if args.out is not None:
        paths = write_watch_results(Path(args.out), view, watched)
        console.print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def run_stop(args: argparse.Namespace, console: Console) -> int:
    settings, keys = connection(args)
    stopped, still, took = asyncio.run(stop_fleet(settings, keys, args.reason, args.timeout))
    if stopped:
        console.print(f"stopped: {', '.join(stopped)} (tokens gone {took:.3f} s after ctl/stop)")
    if still:
        raise RunFailure(f"still alive after {args.timeout:g} s: {', '.join(still)}")
    return 0


def _common(p: argparse.ArgumentParser, timeout: float, waits_for: str) -> None:
    p.add_argument(
        "--connect",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="a robot's (or router's) Zenoh endpoint, e.g. tcp/10.0.0.5:7447; repeat for failover",
    )
    p.add_argument("--fleet", required=True, help="the fleet name (semfleet/<fleet>/...)")
    p.add_argument(
        "--mode",
        choices=MODES,
        default="client",
        help="Zenoh client (default: the reached robot routes for us) or peer (gossip scouting)",
    )
    p.add_argument("--zenoh-config", help="a Zenoh JSON5 file applied first (TLS, access control)")
    p.add_argument(
        "--timeout",
        type=float,
        default=timeout,
        help=f"seconds to wait for {waits_for} (default {timeout:g})",
    )


def add_parser(sub: Any) -> None:
    p = sub.add_parser("fleet", help="see and stop a running fleet from outside (operator)")
    actions = p.add_subparsers(dest="action_name", required=True, metavar="ACTION")
    status = actions.add_parser("status", help="who is alive, steps, counters (one snapshot)")
    _common(status, 2.0, "the robots' answers")
    status.add_argument("--json", action="store_true", help="a JSON document instead of a table")
    status.set_defaults(run=run_status)
    watch = actions.add_parser("watch", help="a live table until Ctrl-C, SIGTERM or --duration")
    _common(watch, 10.0, "the first robot")
    watch.add_argument("--duration", type=float, help="stop watching after this many seconds")
    watch.add_argument("--out", help="write estimates.json and map.png here when the watch ends")
    watch.set_defaults(run=run_watch)
    stop = actions.add_parser("stop", help="ctl/stop, then wait until every token is gone")
    _common(stop, 5.0, "every token to go")
    stop.add_argument("--reason", default="operator stop", help="the reason the agents log")
    stop.set_defaults(run=run_stop)


__all__ = [
    "FleetView",
    "add_parser",
    "collect_status",
    "estimates_doc",
    "mixture_moments",
    "stop_fleet",
    "watch_fleet",
]
