"""Slots and stacks, and the merge rule (design doc §5)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

from estimator.summary import Slot

__all__ = ["Slot", "Stack"]


@dataclass(frozen=True, slots=True, eq=False)
class Stack:
    """One slot per known robot, newest version each."""

    slots: tuple[Slot, ...] = ()

    def __post_init__(self) -> None:
        owners = [s.owner for s in self.slots]
        if len(set(owners)) != len(owners):
            raise ValueError(f"a stack holds one slot per robot, got owners {owners}")
        object.__setattr__(self, "slots", tuple(sorted(self.slots, key=lambda s: s.owner)))

    def __iter__(self) -> Iterator[Slot]:
        return iter(self.slots)

    def __len__(self) -> int:
        return len(self.slots)

    def by_owner(self) -> dict[str, Slot]:
        return {s.owner: s for s in self.slots}

    def stamps(self) -> dict[str, int]:
        """Owner → stamp of the version held."""
        return {s.owner: s.stamp for s in self.slots}

    def with_slot(self, slot: Slot) -> Stack:
        """This stack with ``slot`` replacing its owner's version (used for one's own slot)."""
        others = [s for s in self.slots if s.owner != slot.owner]
        return Stack((*others, slot))

    def merge(self, incoming: Iterable[Slot], own: str) -> Stack:
        """Keep the newest version of every slot; never take a version of ``own``'s slot from
        someone else. Idempotent, commutative and associative on versions (an owner's stamp
        identifies its content); on equal stamps the version already held is kept."""
        held = self.by_owner()
        for slot in incoming:
            if slot.owner == own:
                continue
            current = held.get(slot.owner)
            if current is None or slot.stamp > current.stamp:
                held[slot.owner] = slot
        return Stack(tuple(held.values()))

    def newer_than(self, used: Mapping[str, int], own: str) -> list[Slot]:
        """Slots (never ``own``'s) whose stamp is newer than the version ``used`` records."""
        return [s for s in self.slots if s.owner != own and s.stamp > used.get(s.owner, -1)]
