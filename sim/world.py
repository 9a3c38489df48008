"""Ground truth of a scenario: trajectories, what each robot sees, who can talk to whom."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from estimator.models import se2
from sim.recording import Recording, cached_recording
from sim.scenario import Scenario

Array = NDArray[np.float64]


def integrate(start: Array, actions: Array) -> Array:
    """Poses x_0..x_T (T+1, 3) from a start (3,) and body-frame actions (T, 3)."""
    poses = np.empty((len(actions) + 1, 3))
    poses[0] = start
    for k, a in enumerate(actions):
        poses[k + 1] = se2.compose(poses[k], a)
    return poses


def in_view(pose: Array, points: Array, half_angle: float, max_range: float) -> NDArray[np.bool_]:
    """Which world points (n, 2) a camera at ``pose`` (3,) sees: range and |bearing| tests."""
    rel = se2.transform_to(pose, points)
    dist = np.hypot(rel[..., 0], rel[..., 1])
    bearing = np.arctan2(rel[..., 1], rel[..., 0])
    return np.asarray((dist <= max_range) & (np.abs(bearing) <= half_angle))


@dataclass(frozen=True)
class World:
    """A scenario with its ground truth evaluated. Steps are k = 1..steps; pose index k is x_k."""

    scenario: Scenario

    @cached_property
    def recording(self) -> Recording | None:
        """The scenario's recorded run (``[recording]``), or None for a simulated world."""
        ref = self.scenario.recording
        return None if ref is None else cached_recording(ref.path, ref.sha256)

    @cached_property
    def trajectories(self) -> dict[str, Array]:
        """Robot id → true poses (steps + 1, 3), row k = x_k (row 0 = start); a recorded
        run's own ground truth."""
        rec = self.recording
        if rec is not None:
            return {r: rec.truth[i] for i, r in enumerate(rec.robots)}
        return {
            r.id: integrate(np.asarray(r.start, float), np.asarray(r.actions, float).reshape(-1, 3))
            for r in self.scenario.robots
        }

    @cached_property
    def object_poses(self) -> Array:
        """(n, 3) object poses in scenario order."""
        return self.scenario.object_poses()

    @cached_property
    def visibility(self) -> dict[str, NDArray[np.bool_]]:
        """Robot id → (steps + 1, n) booleans; row k says which objects are seen from x_k.

        Row 0 is all False: the first observation is made at k = 1, after the first action. A
        recorded run's rows are what its robots detected.
        """
        rec = self.recording
        if rec is not None:
            column = {oid: j for j, oid in enumerate(self.scenario.object_ids)}
            seen = {}
            for i, rid in enumerate(rec.robots):
                vis = np.zeros((rec.steps + 1, len(column)), dtype=bool)
                mine = rec.det_robot == i
                cols = [column[int(o)] for o in rec.det_object[mine]]
                vis[rec.det_step[mine], cols] = True
                seen[rid] = vis
            return seen
        out = {}
        pts = self.object_poses[:, :2]
        for r in self.scenario.robots:
            traj = self.trajectories[r.id]
            vis = in_view(traj[:, None, :], pts[None, :, :], r.sensor.half_angle, r.sensor.range)
            vis[0] = False
            out[r.id] = vis
        return out

    def visible_objects(self, robot: str, k: int) -> list[int]:
        """Ids of the objects robot ``robot`` sees at step ``k`` (scenario order)."""
        ids = self.scenario.object_ids
        return [ids[j] for j in np.flatnonzero(self.visibility[robot][k])]

    def known_objects(self, robot: str, k: int) -> list[int]:
        """Ids of the objects robot ``robot`` has seen at any step 1..k (scenario order)."""
        ids = self.scenario.object_ids
        return [ids[j] for j in np.flatnonzero(self.visibility[robot][: k + 1].any(axis=0))]

    def first_sighting(self, robot: str) -> int | None:
        """First step at which ``robot`` sees any object, or None."""
        steps = np.flatnonzero(self.visibility[robot].any(axis=1))
        return int(steps[0]) if len(steps) else None

    def distance(self, a: str, b: str, k: int) -> float:
        """True distance between robots a and b at step k."""
        pa, pb = self.trajectories[a][k], self.trajectories[b][k]
        return float(np.hypot(*(pa[:2] - pb[:2])))

    def links(self, k: int) -> set[tuple[str, str]]:
        """Pairs (a, b), a before b in scenario order, that may exchange stacks at the start of
        step k (the stacks the robots had at the end of step k − 1).

        Range is evaluated on the true positions x_k, which makes the 10 m rule and the paper's
        table agree on r1 joining at k = 13.
        """
        comm = self.scenario.communication
        order = {rid: i for i, rid in enumerate(self.scenario.robot_ids)}
        scheduled: set[tuple[str, str]] = set()
        for e in comm.schedule:
            if e.first <= k <= e.last:
                a, b = sorted((e.a, e.b), key=order.__getitem__)
                scheduled.add((a, b))
        ids = self.scenario.robot_ids
        in_range: set[tuple[str, str]] = set()
        if comm.range is not None:
            in_range = {
                (a, b)
                for i, a in enumerate(ids)
                for b in ids[i + 1 :]
                if self.distance(a, b, k) <= comm.range
            }
        if comm.mode == "schedule":
            return scheduled
        if comm.mode == "range":
            return in_range
        return scheduled & in_range
