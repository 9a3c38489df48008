"""Holding times (issue 47, item 1; docs/wire.md, "Holding times"): how old the information about
each peer is when this robot uses it, on a fleet without a shared clock.

Every stack a robot sends in real time with ask gossip says, per slot, how many milliseconds
have passed since the slot's owner ended the step that made it (``age``): the owner's own wait
from the end of that step to the send, plus, at every robot that relayed it, the time from the
stack's arrival in that robot's inbox to its own send. A robot reads each of those on its own
monotonic clock, so no clock is shared; the transits themselves (a fraction of a millisecond on
loopback, a few on a LAN) are not counted. When this robot's estimate shows its fusion, the age
of each peer's fused version is what the stack said plus the time since it arrived here: the
robot's age of information about that peer. The estimate reports the median and the largest of
them (counters ``peer_age_median_ms``, ``peer_age_max_ms``, over ``peers_aged`` peers);
``semfleet fleet status`` shows them.

A version whose age is not known (it came in a stack without ``age``: from an agent of an
earlier version, a full or lock-step stack, or a journal replay) is left out of the report, and
a stack that would carry one goes without ``age`` at all: an age is never guessed.

Ages are what the senders say. A member may lie about them: that changes the figures reported
and, in a full stack, which held slot is let go of first (``agents.node``; docs/wire.md, "Holding
times": never one whose versions keep coming first from honest peers). Bounded: the last ``KEEP``
versions of at most ``max_owners`` owners.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from statistics import median

from protocol.codec import MAX_AGE_MS

Version = tuple[int, int]  # (epoch, stamp)
# Versions kept per owner: D may fuse a version older than the newest held (a step that
# catches up defers its fusion), so the last few keep their ages.
KEEP = 4
Aging = tuple[tuple[int, float], ...]  # per slot of a stack: (age carried in, held since)


class Ages:
    """The age each held slot version came with and when it came (module docstring)."""

    def __init__(self, robot: str, max_owners: int) -> None:
        self.robot = robot
        self.max_owners = max_owners
        self._held: dict[str, dict[Version, tuple[int, float] | None]] = {}

    def took(self, owner: str, version: Version, carried: int | None, at: float) -> None:
        """``owner``'s ``version`` came at ``at`` (this robot's clock) in a stack that said it was
        ``carried`` ms old then (None: not said)."""
        versions = self._held.pop(owner, {})
        versions[version] = None if carried is None else (carried, at)
        while len(versions) > KEEP:
            del versions[next(iter(versions))]
        self._held[owner] = versions
        while len(self._held) > self.max_owners:
            del self._held[next(iter(self._held))]

    def aging(self, owners: Iterable[str], held: Mapping[str, Version]) -> Aging | None:
        """Per owner in ``owners`` (the slots of a stack, in its order), the age its held version
        came with and since when it is held; None if any is not known."""
        out = []
        for owner in owners:
            known = self._held.get(owner, {}).get(held[owner])
            if known is None:
                return None
            out.append(known)
        return tuple(out)

    def held_ages(
        self, owners: Iterable[str], held: Mapping[str, Version], now: float
    ) -> dict[str, int]:
        """The age (ms) at ``now`` of the held version (``held``) of each of ``owners`` whose age
        is known: what a full stack compares to let go of the oldest information
        (``agents.node``, the neighbourhood bound)."""
        out = {}
        for owner in owners:
            known = self._held.get(owner, {}).get(held.get(owner, (-1, -1)))
            if known is not None:
                out[owner] = known[0] + max(0, round(1000 * (now - known[1])))
        return out

    def report(self, fused: Mapping[str, int], now: float) -> dict[str, int]:
        """The counters of an estimate made at ``now``: median and largest age (ms) of the
        versions D has fused (``fused``: owner → stamp) whose age is known, and how many."""
        ages = []
        for owner, stamp in fused.items():
            if owner == self.robot:
                continue
            known = [a for (_, s), a in self._held.get(owner, {}).items() if s == stamp and a]
            if known:
                carried, since = known[-1]
                ages.append(min(MAX_AGE_MS, carried + max(0, round(1000 * (now - since)))))
        return {
            "peers_aged": len(ages),
            "peer_age_median_ms": round(median(ages)) if ages else 0,
            "peer_age_max_ms": max(ages, default=0),
        }


def stamped_ages(aging: Aging, now: float) -> list[int]:
    """The ages of a stack's slots when it is sent at ``now``."""
    return [carried + max(0, round(1000 * (now - since))) for carried, since in aging]
