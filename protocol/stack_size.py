"""The largest stack message a fleet of one belief configuration can send (issue 43, finding 4).

A receiver refuses a stack by its size before decoding anything (``Limits.max_message_bytes``,
checked first by ``protocol.codec.decode``). The codec's default, 32 MiB, is what the largest
slots the limits allow need: 512 objects with a dense Λ (9.4 MB each) or realisation tables. A
fleet of per-object class beliefs (the default) sends far less: each slot carries n ≤
``max_objects`` objects with M class log φ and a ξ whose form the configuration fixes (dense up
to ``estimator.hybrid.SPARSE_XI_ABOVE`` objects and sparse above for ``xi = "auto"``), and a
stack holds at most
one slot per robot of the roster. :func:`largest_stack_bytes` adds up what the codec writes for
the largest such stack, field by field, so that a receiver can refuse anything larger unread: a
member's 10 MB slot on a 3-robot fleet is refused by its size at 0.73 MB (M = 3) instead of being
decoded.
"""

from __future__ import annotations

from protocol.codec import MAX_EDGES_PER_OBJECT, Limits
from protocol.signing import SIGNATURE_BYTES

ID_BYTES = 32 + 1  # a robot id (1–32 characters) with its msgpack header
BIN = 5  # the header of a msgpack bin or array of up to 2³² − 1 items
INT = 9  # a msgpack integer at most
# Per slot besides its arrays: the keys, owner, stamp, epoch, kind, dim, m, the ξ form, and the
# signature with its header.
SLOT_FIXED = 160 + ID_BYTES + SIGNATURE_BYTES + 2
# Per stack besides its slots: the keys, version, type, sender, step and position; per robot
# of the roster one digest entry (owner, epoch, stamp) and one ask (owner, relay).
STACK_FIXED = 96 + ID_BYTES + 2 * INT
PER_ROBOT = (2 + ID_BYTES + 2 * INT) + (2 + 2 * ID_BYTES)


def per_object_slot_bytes(n: int, m: int, xi: str, dim: int = 3) -> int:
    """Wire bytes of a per-object slot of ``n`` objects and ``m`` classes at most, with a
    ``xi`` of form "dense" or "sparse" (``MAX_EDGES_PER_OBJECT`` edges per object)."""
    ids = BIN + 5 * n  # uint32 ids
    phi = BIN + 4 * n * m  # float32
    lin = BIN + 8 * dim * n  # float64
    if xi == "dense":
        k = dim * n
        xi_bytes = lin + (BIN + 8 * k * (k + 1) // 2) + (BIN + 8 * k)  # Λ's upper triangle, η
    elif xi == "sparse":
        edges = MAX_EDGES_PER_OBJECT * n
        upper = dim * (dim + 1) // 2
        diag, pairs = BIN + 4 * upper * n, BIN + 4 * edges  # float32 blocks, uint16 pairs
        xi_bytes = lin + diag + pairs + (BIN + 4 * dim * dim * edges) + (BIN + 4 * dim * n)
    else:
        raise ValueError(f"ξ form {xi!r} (dense or sparse)")
    return SLOT_FIXED + ids + phi + xi_bytes


def largest_stack_bytes(
    limits: Limits, robots: int, classes: str, xi: str, dense_up_to: int, dim: int = 3
) -> int:
    """The largest stack message a fleet of ``robots`` can send within ``limits`` when every
    robot's belief has ``classes`` ("per_object", else a realisation table) and ``xi`` ("auto":
    dense up to ``dense_up_to`` objects, sparse above; "dense"; "sparse"):
    ``limits.max_message_bytes`` for realisation tables (no tighter bound), else at most one
    slot per robot (and ``max_slots``), each as large as the form allows."""
    if classes != "per_object":
        return limits.max_message_bytes
    n, m = limits.max_objects, limits.num_classes
    if xi == "auto":
        slot = max(
            per_object_slot_bytes(min(n, dense_up_to), m, "dense", dim),
            per_object_slot_bytes(n, m, "sparse", dim),
        )
    else:
        slot = per_object_slot_bytes(n, m, xi, dim)
    slots = max(1, min(robots, limits.max_slots))
    return min(limits.max_message_bytes, STACK_FIXED + PER_ROBOT * slots + slot * slots)
