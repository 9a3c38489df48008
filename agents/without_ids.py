"""What a node whose frames carry no global ids adds around D's step (issue 45): D takes the
detections its L left unconfirmed that pair with objects only peers inform D of, and the held
peers' slots are matched again when L confirms objects (docs/estimator.md, "Data association
across the fleet"). L, the robot's own data, is never touched here."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Protocol

from estimator.association import Association, Associator
from estimator.distributed import DistributedBelief
from estimator.models import Detection, SensorFrame
from estimator.summary import Slot

Replay = tuple[tuple[str, int, Detection], ...]


class Track(Protocol):
    """What is read of a robot's local track (``agents.node.LocalTrack``)."""

    association: Association | None
    associator: Associator | None

    def replay_of(self, frame: SensorFrame) -> Replay: ...


class WithoutIds:
    """One node's state for frames without global ids: ``took`` (step, L's tentative track) of
    the detections D took for a peer's object, left out of that object's replay into D when L
    confirms it (bounded by L's tentative objects); ``again``: a rematch left proposals
    pending, matched once more at the next step; counters ``peer_sightings`` (detections D
    took) and ``rematches`` (rematches that changed a mapping)."""

    def __init__(self) -> None:
        self.took: set[tuple[int, int]] = set()
        self.again = False
        self.peer_sightings = 0
        self.rematches = 0

    def for_d(
        self, track: Track, d: DistributedBelief, frame: SensorFrame, stepped: SensorFrame
    ) -> tuple[list[SensorFrame], Replay]:
        """D's frames and replay for the frame ``stepped`` that L stepped on (``frame`` as it
        came): the detections L left unconfirmed are paired with D's objects that only peers
        inform (``Associator.pair``), and D takes those pairings at once, as with given ids a
        single sighting of a peer's object ties the robot to the peer's map."""
        replay = track.replay_of(stepped)
        a, fleet, associator = track.association, d.association, track.associator
        if a is None or a.frame is not stepped or fleet is None or associator is None:
            return [stepped], replay
        if self.took:
            replay = tuple(r for r in replay if (r[1], r[2].object_id) not in self.took)
            live = {t.track for t in associator.tentative}
            self.took = {(k, t) for k, t in self.took if t in live}
        left = [i for i, entered in enumerate(a.entered) if not entered]
        fresh = [j for j in d.object_ids if fleet.is_fresh(j)]
        if not left or not fresh:
            return [stepped], replay
        sub = replace(frame, detections=tuple(frame.detections[i] for i in left))
        extra = []
        for i, j in sorted(associator.pair(d, sub, fresh).items()):
            det = sub.detections[i]
            extra.append(Detection(j, det.z_geo, det.z_sem))
            self.took.add((frame.k, a.tracks[left[i]]))
        self.peer_sightings += len(extra)
        return [replace(stepped, detections=stepped.detections + tuple(extra))], replay

    def rematch_due(self, track: Track, stepped: SensorFrame) -> bool:
        """Whether L confirmed objects at ``stepped``, or a rematch is to be repeated."""
        a = track.association
        return self.again or (a is not None and a.frame is stepped and bool(a.confirmed))

    def rematch(self, d: DistributedBelief, held: Sequence[Slot]) -> bool:
        """Match the ``held`` peers' slots again (``FleetAssociation.rematch``); whether a
        mapping changed, so that D must be rebuilt. A move waits for a second proposal (the
        mappings' hysteresis): proposals left pending are matched once more at the next step,
        not at the owner's next version."""
        again, self.again = self.again, False
        fleet = d.association
        if fleet is None or not fleet.maps:
            return False
        changed = fleet.rematch(d, held)
        self.rematches += changed
        self.again = not again and any(m.pending for m in fleet.maps.values())
        return changed

    def rebuilt(self) -> None:
        """D was made anew from L and the slots: it holds none of the detections it took."""
        self.took.clear()
