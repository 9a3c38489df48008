"""How well a robot associated its frames without global ids (``estimator.association``),
scored against the simulator's truth of every detection (``sim.sensors.Simulator.labels``): the
truth stays here, in the study, and never reaches the robot.

Per robot, a detection *matched* an object when it went to a track that existed before its
frame; the match is *right* when that track's detections so far were mostly of the detection's
true object. ``precision`` = right / matched; ``recall`` = right / matchable, the detections of
true objects the robot had detected before. At the end: ``wrong_merges``, the objects (or
clutter) beyond the first that a map object's detections hold; ``splits``, the map objects
beyond the first whose detections are mostly one true object; ``confirmed_clutter``, map objects
made mostly of false detections; ``clutter_entered``, false detections that reached the belief;
``searches_cut``, frames whose joint search stopped at its budget (``AssociationConfig.budget``).

Across the fleet (``estimator.fleet_association``): at a run's end, every receiver's mapping of
every owner's objects onto its D, each owner object and D object taken as the true object its
robot's tally gives (:func:`fleet_counts`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field

from agents.node import RobotNode
from estimator.association import Association
from sim.sensors import CLUTTER

# What a run records per method (sums over robots), in results.json's order.
COUNTS = (
    "frames",
    "detections",
    "matched",
    "right",
    "matchable",
    "wrong_merges",
    "splits",
    "confirmed",
    "confirmed_clutter",
    "clutter_entered",
    "searches_cut",
)


@dataclass(slots=True)
class AssociationTally:
    """One robot's association decisions and their truth, frame by frame."""

    counts: dict[int, Counter[int]] = field(default_factory=dict)  # track → true label → n
    seen: set[int] = field(default_factory=set)  # true objects detected so far
    figures: Counter[str] = field(default_factory=Counter)
    ms: list[float] = field(default_factory=list)

    def add(self, a: Association, labels: Sequence[int], ms: float = 0.0) -> None:
        """One frame's association ``a`` and the truth of its detections, in frame order."""
        f = self.figures
        f["frames"] += 1
        f["detections"] += len(labels)
        f["searches_cut"] += a.cut
        self.ms.append(ms)
        for track, label, entered in zip(a.tracks, labels, a.entered, strict=True):
            before = self.counts.get(track)
            if before:
                f["matched"] += 1
                f["right"] += label != CLUTTER and before.most_common(1)[0][0] == label
            if label != CLUTTER and label in self.seen:
                f["matchable"] += 1
            f["clutter_entered"] += label == CLUTTER and entered
        for track, label in zip(a.tracks, labels, strict=True):
            self.counts.setdefault(track, Counter())[label] += 1
            if label != CLUTTER:
                self.seen.add(label)

    def truth_of(self, tracks: Collection[int]) -> dict[int, int]:
        """Map object → the true object most of its detections are (``CLUTTER`` for false
        ones): what its estimate is scored against."""
        return {t: self.counts[t].most_common(1)[0][0] for t in tracks if t in self.counts}

    def final(self, confirmed: Collection[int]) -> dict[str, int]:
        """Every figure of :data:`COUNTS`, the map objects being ``confirmed``."""
        out = {name: int(self.figures[name]) for name in COUNTS}
        majority = self.truth_of(confirmed)
        out["confirmed"] = len(majority)
        out["wrong_merges"] = sum(len(self.counts[t]) - 1 for t in majority)
        out["confirmed_clutter"] = sum(label == CLUTTER for label in majority.values())
        per_object = Counter(label for label in majority.values() if label != CLUTTER)
        out["splits"] = sum(n - 1 for n in per_object.values())
        return out


def summarise(counts: Mapping[str, float], ms: Sequence[float]) -> dict[str, float]:
    """results.json's ``association`` entry: the counts, precision, recall and the time per
    frame (mean and 99th percentile, ms)."""
    out = {name: float(counts.get(name, 0)) for name in COUNTS}
    out["precision"] = out["right"] / out["matched"] if out["matched"] else float("nan")
    out["recall"] = out["right"] / out["matchable"] if out["matchable"] else float("nan")
    ordered = sorted(ms)
    out["ms_mean"] = sum(ordered) / len(ordered) if ordered else float("nan")
    out["ms_p99"] = (
        ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] if ordered else float("nan")
    )
    return out


# -- across the fleet (estimator.fleet_association) ---------------------------------------------

# What a fleet run records per method (sums over receivers and owners at the run's end), in
# results.json's order (:func:`fleet_counts`): ``owner_objects`` the peers' objects the
# receivers map, ``matched`` those whose D object holds an object of another source too,
# ``right`` those whose every such other object is their true object, ``matchable`` those whose
# true object D holds from another source, ``pairs`` owner objects × the D objects with another
# source (the denominator of wrong matches per 1,000 pairs), ``changes`` mapping changes over
# the run.
FLEET_COUNTS = ("owner_objects", "matched", "right", "matchable", "pairs", "changes")


def d_truth(node: RobotNode, tallies: Mapping[str, AssociationTally]) -> dict[int, int]:
    """D object id → its true object (``CLUTTER`` for one of false detections): the receiver's
    own through its association's tally, a fresh one through its owner's."""
    fleet = node.distributed.association
    own = tallies[node.robot].truth_of(
        [j for j in node.distributed.object_ids if fleet is None or not fleet.is_fresh(j)]
    )
    if fleet is None:
        return own
    for j in node.distributed.object_ids:
        origin = fleet.origin(j)
        if origin is not None and origin[0] in tallies:
            truth = tallies[origin[0]].truth_of([origin[1]])
            own[j] = truth.get(origin[1], CLUTTER)
    return own


def fleet_counts(
    nodes: Mapping[str, RobotNode], tallies: Mapping[str, AssociationTally]
) -> dict[str, int]:
    """:data:`FLEET_COUNTS` of every receiver's final mappings, against the truth. Each D object
    gathers its *members*: the receiver's own object of that id and every owner object mapped to
    it. An owner object is matched when its D object has a member from another source, right
    when every such member is its true object, matchable when its true object is a member of D
    from another source (own or another owner's)."""
    out = dict.fromkeys(FLEET_COUNTS, 0)
    for node in nodes.values():
        fleet = node.distributed.association
        if fleet is None:
            continue
        out["changes"] += fleet.changes
        members: dict[int, list[tuple[str, int]]] = {}  # D id → (source, true object)
        own = tallies[node.robot].truth_of(
            [j for j in node.distributed.object_ids if not fleet.is_fresh(j)]
        )
        for j, t in own.items():
            members.setdefault(j, []).append(("", t))
        for owner in fleet.maps:
            theirs = tallies[owner].truth_of(list(fleet.mapping(owner)))
            for i, j in fleet.mapping(owner).items():
                members.setdefault(j, []).append((owner, theirs.get(i, CLUTTER)))
        for owner in fleet.maps:
            theirs = tallies[owner].truth_of(list(fleet.mapping(owner)))
            elsewhere = {t for m in members.values() for o, t in m if o != owner} - {CLUTTER}
            targets = sum(any(o != owner for o, _ in m) for m in members.values())
            for i, j in fleet.mapping(owner).items():
                true_i = theirs.get(i, CLUTTER)
                out["owner_objects"] += 1
                out["pairs"] += targets
                out["matchable"] += true_i in elsewhere
                others = [t for o, t in members[j] if o != owner]
                if others:
                    out["matched"] += 1
                    out["right"] += true_i != CLUTTER and all(t == true_i for t in others)
    return out


def fleet_summary(counts: Mapping[str, float]) -> dict[str, float]:
    """results.json's ``fleet_association`` entry: the counts, precision, recall, wrong matches
    and wrong matches per 1,000 object pairs."""
    out = {name: float(counts.get(name, 0)) for name in FLEET_COUNTS}
    wrong = out["matched"] - out["right"]
    out["wrong"] = wrong
    out["precision"] = out["right"] / out["matched"] if out["matched"] else float("nan")
    out["recall"] = out["right"] / out["matchable"] if out["matchable"] else float("nan")
    out["wrong_per_1000_pairs"] = 1000.0 * wrong / out["pairs"] if out["pairs"] else float("nan")
    return out
