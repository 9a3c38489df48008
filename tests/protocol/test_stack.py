"""Stacks and their merge rule (design doc §5): the newest version per owner wins, one's own slot
is never taken from a peer, and the rule is idempotent, commutative and associative.

Slots compare by identity (``eq=False``), so every (owner, epoch, stamp) maps to one shared Slot
object: an owner's version identifies its content, the premise of commutativity. A version is
(epoch, stamp): a robot that lost its journal starts its stamps again under a higher epoch.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.summary import LocalSummary, Realisation, Xi
from protocol.stack import Slot, Stack

OWNERS = ("a", "b", "c", "d", "e")
OWN = "a"
PROPERTY = settings(derandomize=True, deadline=None, max_examples=500)


@functools.cache
def version(owner: str, stamp: int, epoch: int = 0) -> Slot:
    """The one Slot object holding ``owner``'s summary at its step ``stamp`` of ``epoch``."""
    real = Realisation((stamp % 2,), float(stamp), Xi(np.zeros((1, 3)), np.eye(3), np.zeros(3)))
    return Slot(owner, stamp, LocalSummary((stamp,), (real,)), epoch)


def stack_of(stamps: dict[str, int] | dict[str, tuple[int, int]]) -> Stack:
    """From owner → stamp, or owner → (epoch, stamp)."""
    return Stack(
        tuple(
            version(o, v[1], v[0]) if isinstance(v, tuple) else version(o, v)
            for o, v in stamps.items()
        )
    )


# Later epochs with lower stamps are in every draw: a stamp alone would order them wrongly.
EPOCH_STAMP = st.tuples(st.integers(0, 2), st.integers(0, 6))
VERSIONS = st.builds(lambda o, v: version(o, v[1], v[0]), st.sampled_from(OWNERS), EPOCH_STAMP)
BATCHES = st.lists(VERSIONS, max_size=10)
STACKS = st.dictionaries(st.sampled_from(OWNERS), EPOCH_STAMP).map(stack_of)


def _newest(held: Stack, incoming: list[Slot], own: str) -> dict[str, tuple[int, int]]:
    """Reference rule: the greatest (epoch, stamp) seen per owner — the epoch first — and only
    the held one for ``own``."""
    out = held.versions()
    for slot in incoming:
        if slot.owner != own:
            e, s = out.get(slot.owner, (-1, -1))
            if slot.epoch > e or (slot.epoch == e and slot.stamp > s):
                out[slot.owner] = (slot.epoch, slot.stamp)
    return out


@PROPERTY
@given(held=STACKS, incoming=BATCHES)
def test_stack_merge_keeps_newest_version_per_owner(held: Stack, incoming: list[Slot]) -> None:
    merged = held.merge(incoming, OWN)
    expected = _newest(held, incoming, OWN)
    assert merged.versions() == expected
    assert all(slot is version(slot.owner, slot.stamp, slot.epoch) for slot in merged)


def test_a_later_epoch_wins_over_a_higher_stamp() -> None:
    """A robot that lost its journal restarts at stamp 1 under a higher epoch: its new slot
    replaces the old one everywhere, and the old one never comes back."""
    old, new = version("b", 40, 7), version("b", 1, 8)
    assert Stack((old,)).merge([new], OWN).by_owner()["b"] is new
    assert Stack((new,)).merge([old], OWN).by_owner()["b"] is new
    assert [s.owner for s in Stack((new,)).newer_than({"b": (7, 40)}, OWN)] == ["b"]
    assert Stack((old,)).newer_than({"b": (8, 1)}, OWN) == []


@PROPERTY
@given(held=STACKS, incoming=BATCHES)
def test_stack_merge_never_overwrites_own_slot(held: Stack, incoming: list[Slot]) -> None:
    merged = held.merge(incoming, OWN)
    assert merged.by_owner().get(OWN) is held.by_owner().get(OWN)


def test_stack_merge_ignores_newer_own_slot_from_peer() -> None:
    held = stack_of({OWN: 1})
    merged = held.merge([version(OWN, 5)], OWN)
    assert merged.by_owner()[OWN] is version(OWN, 1)
    assert Stack().merge([version(OWN, 5)], OWN).stamps() == {}


def test_stack_merge_keeps_held_version_on_equal_stamps() -> None:
    held = version("b", 3)
    rival = Slot("b", 3, held.summary)
    assert Stack((held,)).merge([rival], OWN).by_owner()["b"] is held
    assert Stack((held,)).merge([version("b", 2)], OWN).by_owner()["b"] is held


@PROPERTY
@given(held=STACKS, incoming=BATCHES)
def test_stack_merge_returns_the_stack_itself_when_nothing_is_newer(
    held: Stack, incoming: list[Slot]
) -> None:
    merged = held.merge(incoming, OWN)
    newer = any(
        s.owner != OWN and s.version > (held.version_of(s.owner) or (-1, -1)) for s in incoming
    )
    assert (merged is not held) == newer
    assert merged.merge(incoming, OWN) is merged


@PROPERTY
@given(held=STACKS, incoming=BATCHES)
def test_stack_merge_is_idempotent(held: Stack, incoming: list[Slot]) -> None:
    once = held.merge(incoming, OWN)
    assert once.merge(incoming, OWN).slots == once.slots
    assert once.merge(once, OWN).slots == once.slots
    assert held.merge(held, OWN).slots == held.slots


@PROPERTY
@given(held=STACKS, first=BATCHES, second=BATCHES)
def test_stack_merge_is_commutative(held: Stack, first: list[Slot], second: list[Slot]) -> None:
    one_way = held.merge(first, OWN).merge(second, OWN)
    other_way = held.merge(second, OWN).merge(first, OWN)
    assert one_way.slots == other_way.slots
    assert held.merge(first + second, OWN).slots == held.merge(second + first, OWN).slots
    assert held.merge(first + second, OWN).slots == one_way.slots


@PROPERTY
@given(held=STACKS, peers=st.lists(STACKS, min_size=1, max_size=4), data=st.data())
def test_stack_merge_of_simultaneous_deliveries_is_order_free(
    held: Stack, peers: list[Stack], data: st.DataObject
) -> None:
    reference = held
    for peer in peers:
        reference = reference.merge(peer, OWN)
    order = data.draw(st.permutations(peers))
    shuffled = held
    for peer in order:
        shuffled = shuffled.merge(peer, OWN)
    assert shuffled.slots == reference.slots
    flat = list(itertools.chain.from_iterable(order))
    assert held.merge(flat, OWN).slots == reference.slots


@PROPERTY
@given(x=STACKS, y=STACKS, z=STACKS)
def test_stack_merge_is_associative(x: Stack, y: Stack, z: Stack) -> None:
    left = x.merge(y, OWN).merge(z, OWN)
    right = x.merge(y.merge(z, OWN), OWN)
    assert left.slots == right.slots


@PROPERTY
@given(held=STACKS, incoming=BATCHES)
def test_stack_merge_leaves_the_original_untouched(held: Stack, incoming: list[Slot]) -> None:
    before = held.slots
    held.merge(incoming, OWN)
    assert held.slots == before


def test_stack_rejects_duplicate_owners() -> None:
    with pytest.raises(ValueError, match="one slot per robot"):
        Stack((version("b", 1), version("b", 2)))
    with pytest.raises(ValueError, match="one slot per robot"):
        Stack((version("b", 1), version("c", 1), version("b", 1)))


@PROPERTY
@given(stamps=st.dictionaries(st.sampled_from(OWNERS), st.integers(0, 6)), data=st.data())
def test_stack_orders_slots_by_owner(stamps: dict[str, int], data: st.DataObject) -> None:
    slots = data.draw(st.permutations([version(o, s, s % 3) for o, s in stamps.items()]))
    stack = Stack(tuple(slots))
    assert [s.owner for s in stack] == sorted(stamps)
    assert len(stack) == len(stamps)
    assert stack.stamps() == stamps
    assert stack.versions() == {o: (s % 3, s) for o, s in stamps.items()}
    assert stack.by_owner() == {s.owner: s for s in slots}


@PROPERTY
@given(
    stack=STACKS,
    used=st.dictionaries(st.sampled_from(OWNERS), st.tuples(st.integers(0, 2), st.integers(-1, 7))),
    own=st.sampled_from(OWNERS),
)
def test_stack_newer_than_lists_unused_versions(
    stack: Stack, used: dict[str, tuple[int, int]], own: str
) -> None:
    def newer(s: Slot) -> bool:
        e, k = used.get(s.owner, (-1, -1))
        return s.epoch > e or (s.epoch == e and s.stamp > k)

    expected = [s for s in stack if s.owner != own and newer(s)]
    assert stack.newer_than(used, own) == expected


def test_stack_newer_than_examples() -> None:
    stack = stack_of({"a": 3, "b": 0, "c": 2, "d": 5})
    assert [s.owner for s in stack.newer_than({}, "a")] == ["b", "c", "d"]
    assert [s.owner for s in stack.newer_than({"b": (0, 0), "c": (0, 1), "d": (0, 5)}, "a")] == [
        "c"
    ]
    assert stack.newer_than({"b": (0, 0), "c": (0, 2), "d": (0, 5)}, "a") == []
    assert [s.owner for s in stack.newer_than({"b": (0, 0), "c": (0, 2), "d": (0, 5)}, "e")] == [
        "a"
    ]


@PROPERTY
@given(stack=STACKS, slot=VERSIONS)
def test_stack_with_slot_replaces_its_owners_version(stack: Stack, slot: Slot) -> None:
    replaced = stack.with_slot(slot)
    assert replaced.by_owner()[slot.owner] is slot
    others = {o: s for o, s in stack.by_owner().items() if o != slot.owner}
    assert {o: s for o, s in replaced.by_owner().items() if o != slot.owner} == others
    assert len(replaced) == len(others) + 1


def test_stack_with_slot_replaces_even_with_an_older_stamp() -> None:
    # with_slot is how a robot installs its own new slot: unconditional, unlike merge.
    stack = stack_of({"a": 5, "b": 1})
    assert stack.with_slot(version("a", 2)).stamps() == {"a": 2, "b": 1}
