"""Slots and stacks, and the merge rule (design doc §5): the newest *version* of each owner's
slot, a version being (epoch, stamp) (docs/wire.md, "Versions and epochs")."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

from estimator.summary import Slot

__all__ = ["Slot", "Stack"]


@dataclass(frozen=True, slots=True, eq=False)
class Stack:
    """One slot per known robot, newest version each."""

    slots: tuple[Slot, ...] = ()
    # owner → (epoch, stamp), made once: a receiver asks for it for every slot header it reads
    _versions: dict[str, tuple[int, int]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        owners = [s.owner for s in self.slots]
        if len(set(owners)) != len(owners):
            raise ValueError(f"a stack holds one slot per robot, got owners {owners}")
        object.__setattr__(self, "slots", tuple(sorted(self.slots, key=lambda s: s.owner)))
        object.__setattr__(self, "_versions", {s.owner: s.version for s in self.slots})

    def __iter__(self) -> Iterator[Slot]:
        return iter(self.slots)

    def __len__(self) -> int:
        return len(self.slots)

    def by_owner(self) -> dict[str, Slot]:
        return {s.owner: s for s in self.slots}

    def stamps(self) -> dict[str, int]:
        """Owner → stamp of the version held (for people; compare :meth:`versions`)."""
        return {s.owner: s.stamp for s in self.slots}

    def versions(self) -> dict[str, tuple[int, int]]:
        """Owner → (epoch, stamp) of the version held (a new dict: the caller may change it)."""
        return dict(self._versions)

    def version_of(self, owner: str) -> tuple[int, int] | None:
        """The (epoch, stamp) held of ``owner``'s slot, None if none is held."""
        return self._versions.get(owner)

    def with_slot(self, slot: Slot) -> Stack:
        """This stack with ``slot`` replacing its owner's version (used for one's own slot)."""
        others = [s for s in self.slots if s.owner != slot.owner]
        return Stack((*others, slot))

    def merge(self, incoming: Iterable[Slot], own: str) -> Stack:
        """Keep the newest version (epoch, stamp) of every slot; never take a version of
        ``own``'s slot from someone else. Idempotent, commutative and associative on versions (an
        owner's version identifies its content); on equal versions the one held is kept."""
        held = self.by_owner()
        newer = False
        for slot in incoming:
            if slot.owner == own:
                continue
            current = held.get(slot.owner)
            if current is None or slot.version > current.version:
                held[slot.owner] = slot
                newer = True
        return Stack(tuple(held.values())) if newer else self  # most gossip brings nothing new

    def newer_than(self, used: Mapping[str, tuple[int, int]], own: str) -> list[Slot]:
        """Slots (never ``own``'s) whose version is newer than the one ``used`` records."""
        return [s for s in self.slots if s.owner != own and s.version > used.get(s.owner, NONE)]


NONE = (-1, -1)  # older than every version
