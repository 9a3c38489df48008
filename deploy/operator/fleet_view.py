"""The operator's picture of a running fleet, sans-I/O: who is alive, every robot's latest
estimate and its trail (:class:`FleetView`, fed liveliness changes and estimate bytes with
``now``), and the documents drawn from it — ``fleet status --json`` and estimates.json
(docs/results.md, "Fleet estimates"), which :func:`write_watch_results` saves with its map.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.transport.base import Keys, Message
from estimator.hybrid import BeliefSnapshot
from estimator.metrics import mixture_moments
from protocol.errors import RemoteProtocolError
from protocol.estimate import EstimateLimits, EstimateMessage, decode_estimate

Array = NDArray[np.float64]

RESULTS_FORMAT = 1


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


def belief_doc(snap: BeliefSnapshot, num_classes: int) -> dict[str, Any]:
    """One belief for estimates.json (docs/results.md, "Fleet estimates")."""
    top = int(np.argmax(snap.weights))
    robot_pose, robot_cov = mixture_moments(snap.weights, snap.robot_pose, snap.robot_cov)
    obj_pose, obj_cov = mixture_moments(snap.weights, snap.object_pose, snap.object_cov)
    marginals = snap.marginals(num_classes)
    if marginals.shape[1] < num_classes:  # per-object marginals of fewer classes than are seen
        marginals = np.pad(marginals, ((0, 0), (0, num_classes - marginals.shape[1])))
    # MAP class: the top hypothesis' (a realisation table), or the most probable per object
    if snap.class_probs is None:
        map_class = snap.classes[top]
    else:
        map_class = np.argmax(snap.class_probs, axis=1)
    objects = [
        {
            "id": int(j),
            "map_class": int(map_class[i]),
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
    """1 + the largest class index any hypothesis holds, or M of a belief with per-object class
    marginals (``class_probs`` (n, M)) if more (a realisation table does not carry M; a class no
    hypothesis holds has probability 0)."""
    top = 0
    for state in view.robots.values():
        if state.estimate is not None:
            for snap in state.estimate.beliefs.values():
                if snap.classes.size:
                    top = max(top, int(snap.classes.max()) + 1)
                if snap.class_probs is not None:
                    top = max(top, snap.class_probs.shape[1])
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


def fusion_behind(view: FleetView) -> dict[str, dict[str, int]]:
    """Per robot i, per peer j whose version it says it fused (``EstimateMessage.fused``) and
    whose own estimate the view holds: how many steps j's latest estimate is ahead of the version
    i's fusion holds, k_j − stamp (0 for a version at least as new: the two estimates answered
    at slightly different times). A staleness every fleet can report without a shared clock."""
    steps = {r: s.estimate.k for r, s in view.robots.items() if s.estimate is not None}
    out: dict[str, dict[str, int]] = {}
    for robot, state in sorted(view.robots.items()):
        fused = state.estimate.fused if state.estimate is not None else None
        if fused is not None:
            out[robot] = {o: max(0, steps[o] - v) for o, v in sorted(fused.items()) if o in steps}
    return out


def behind_line(view: FleetView) -> str:
    """The line under ``fleet status``'s table: the median and largest :func:`fusion_behind`
    (empty when no robot says what it fused)."""
    pairs = [(n, r, o) for r, peers in fusion_behind(view).items() for o, n in peers.items()]
    if not pairs:
        return ""
    n, robot, owner = max(pairs)
    median = float(np.median([p[0] for p in pairs]))
    return (
        f"fusion behind the peers' latest steps over {len(pairs)} (robot, peer): median "
        f"{median:g}, max {n} ({robot} of {owner})"
    )


def age_line(view: FleetView) -> str:
    """The line under ``fleet status``'s table from the robots' holding times (``agents.ages``;
    docs/wire.md, "Holding times"): the median of the robots' median ages of their peers'
    information, and the largest with its robot (empty when no robot reports an age)."""
    aged = [
        (c.get("peer_age_max_ms", 0), c.get("peer_age_median_ms", 0), r)
        for r, s in sorted(view.robots.items())
        if s.estimate is not None and (c := s.estimate.counters).get("peers_aged", 0) > 0
    ]  # counters are a peer's word: one it leaves out reads as 0, never a KeyError
    if not aged:
        return ""
    largest, _, robot = max(aged)
    median = float(np.median([a[1] for a in aged]))
    return (
        f"age of the peers' information (holding times, transits excluded) on {len(aged)} "
        f"robots: median {median:.0f} ms, max {largest} ms ({robot})"
    )


def status_doc(view: FleetView, elapsed_s: float, answered_s: float) -> dict[str, Any]:
    """``fleet status --json``: per robot its token, step, hypotheses, objects, counters, the
    peer versions its fusion holds and how far each is behind (:func:`fusion_behind`)."""
    behind = fusion_behind(view)
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
                "fused": dict(sorted(est.fused.items())) if est and est.fused is not None else None,
                "behind_steps": behind.get(robot),
            }
        )
    return {
        "fleet": view.keys.fleet,
        "elapsed_s": round(elapsed_s, 3),
        "answered_s": round(answered_s, 3) if math.isfinite(answered_s) else None,
        "invalid_estimates": view.invalid,
        "robots": robots,
    }


def write_watch_results(out: Path, view: FleetView, watched_s: float) -> list[Path]:
    """estimates.json and map.png in ``out`` (created)."""
    from deploy.study.plots import write_fleet_map  # matplotlib takes a second to import

    out.mkdir(parents=True, exist_ok=True)
    doc = estimates_doc(view, watched_s)
    path = out / "estimates.json"
    path.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    map_path = out / "map.png"
    write_fleet_map(map_path, doc)
    return [path, map_path]
