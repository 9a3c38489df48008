"""The largest stack a per-object fleet can send (protocol.stack_size): never below what the codec
writes for the largest stack of a configuration, and within a few percent of it."""

from __future__ import annotations

import numpy as np
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from estimator.hybrid import SPARSE_XI_ABOVE
from estimator.sparse_xi import SparseXi
from estimator.summary import LocalSummary, ObjectClasses
from estimator.xi import Xi
from protocol.codec import (
    MAX_EDGES_PER_OBJECT,
    MAX_EPOCH,
    Limits,
    StackMessage,
    decode,
    encode,
    sign_slot,
)
from protocol.errors import LimitExceeded
from protocol.stack import Slot, Stack
from protocol.stack_size import largest_stack_bytes, per_object_slot_bytes

KEY = Ed25519PrivateKey.from_private_bytes(bytes(range(32)))


def _dense(n: int, m: int) -> LocalSummary:
    xi = Xi(np.zeros((n, 3)), np.eye(3 * n), np.full(3 * n, 0.5))
    return LocalSummary(tuple(range(2**32 - n, 2**32)), (), ObjectClasses(np.ones((n, m)), xi))


def _sparse(n: int, m: int) -> LocalSummary:
    """n objects, each with MAX_EDGES_PER_OBJECT edges to the objects after it (the codec's
    most), blocks of zero: a positive definite Λ_s."""
    edges = sorted(
        {
            (i, (i + d) % n) if i < (i + d) % n else ((i + d) % n, i)
            for i in range(n)
            for d in range(1, MAX_EDGES_PER_OBJECT + 1)
        }
    )[: MAX_EDGES_PER_OBJECT * n]
    e = np.array(edges, dtype=np.int64)
    xi = SparseXi(
        np.zeros((n, 3)),
        np.broadcast_to(np.eye(3, dtype=np.float32), (n, 3, 3)).astype(np.float64),
        e,
        np.zeros((len(e), 3, 3)),
        np.full(3 * n, 0.5),
    )
    return LocalSummary(tuple(range(2**32 - n, 2**32)), (), ObjectClasses(np.ones((n, m)), xi))


def _stack(robots: int, summary: LocalSummary) -> bytes:
    """``robots`` signed slots of ``summary`` from robots with 32-character ids, with a digest
    and an ask per robot: the largest a stack of this summary can be."""
    ids = [f"{i:02d}" + "r" * 30 for i in range(robots)]
    slots = tuple(
        sign_slot(Slot(o, 9_999_999, summary, MAX_EPOCH), KEY, Limits(num_classes=64)) for o in ids
    )
    have = {o: (MAX_EPOCH, 9_999_999) for o in ids}
    ask = {o: ids[0] for o in ids}
    message = StackMessage(ids[0], (1e3, -1e3), Stack(slots), 9_999_999, have=have, ask=ask)
    return encode(message, Limits(num_classes=64))


@pytest.mark.parametrize(
    "form, n", [("dense", SPARSE_XI_ABOVE), ("dense", 64), ("sparse", 512), ("sparse", 40)]
)
@pytest.mark.parametrize("m", [3, 20])
def test_the_bound_covers_the_codecs_largest_slot_and_is_tight(form: str, n: int, m: int) -> None:
    summary = _dense(n, m) if form == "dense" else _sparse(n, m)
    for robots in (1, 3):
        wire = len(_stack(robots, summary))
        bound = largest_stack_bytes(
            Limits(num_classes=m, max_objects=n), robots, "per_object", form, SPARSE_XI_ABOVE
        )
        assert wire <= bound <= 1.02 * wire + 512 * robots, (wire, bound)


def test_auto_takes_the_larger_of_its_two_forms() -> None:
    lim = Limits(num_classes=4)
    auto = largest_stack_bytes(lim, 3, "per_object", "auto", SPARSE_XI_ABOVE)
    dense_small = per_object_slot_bytes(SPARSE_XI_ABOVE, 4, "dense")
    sparse_all = per_object_slot_bytes(512, 4, "sparse")
    assert auto > 3 * max(dense_small, sparse_all)
    assert auto < 1_000_000 < largest_stack_bytes(lim, 3, "per_object", "dense", SPARSE_XI_ABOVE)
    # Realisation tables: no tighter bound than the codec's.
    assert largest_stack_bytes(lim, 3, "table", "dense", SPARSE_XI_ABOVE) == lim.max_message_bytes
    # Never above the codec's, and at least one slot for an empty roster.
    assert (
        largest_stack_bytes(lim, 64, "per_object", "dense", SPARSE_XI_ABOVE)
        == lim.max_message_bytes
    )
    assert largest_stack_bytes(
        lim, 0, "per_object", "auto", SPARSE_XI_ABOVE
    ) == largest_stack_bytes(lim, 1, "per_object", "auto", SPARSE_XI_ABOVE)


def test_a_stack_over_the_bound_is_refused_unread() -> None:
    lim = Limits(num_classes=4)
    bound = largest_stack_bytes(lim, 3, "per_object", "auto", SPARSE_XI_ABOVE)
    big = _stack(1, _dense(300, 4))  # a dense ξ over 300 objects: 3.3 MB
    assert len(big) > bound
    decode(big, lim)  # the codec's own 32 MiB let it in
    with pytest.raises(LimitExceeded, match=f"message: .* bytes > {bound}"):
        decode(big, Limits(num_classes=4, max_message_bytes=bound))
