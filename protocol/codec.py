"""The one module that owns ``encode``/``decode`` of the wire format (docs/wire.md).

A message is a msgpack map ``{"v": 1, "type": "stack", "sender": str, "k": int, "pos": [x, y] | nil,
"slots": [...]}``; every float array travels as little-endian float64 bytes (a per-object slot's
class log φ as float32), Λ as its upper triangle. Versions 1 and 2 (signed) carry realisation
tables; 3 and 4 (signed) also per-object slots, whose ``real`` is a map (docs/wire.md,
"Per-object slots"). ``decode`` turns every malformed input into a :class:`RemoteProtocolError`
subclass that names the field; nothing else escapes it.

Over 300 lines for a reason: encode and decode must refuse exactly the same documents, so both
sides of every field, and the limits they share, are kept side by side in this one module.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from numpy.typing import NDArray
from scipy.linalg.lapack import dpotrf

from estimator.models.frames import MAX_STEP
from estimator.sparse_xi import MAX_XI_PARENTS, SparseXi
from estimator.summary import LocalSummary, ObjectClasses, Realisations, WireForm, Xi
from protocol.errors import (
    BadSignature,
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
    UnsupportedVersion,
)
from protocol.scan import SlotFrame, scan
from protocol.signing import (
    SIGNATURE_BYTES,
    SigningKeys,
    digest_of_parts,
    verify_digest,
)
from protocol.stack import Slot, Stack
from protocol.validate import as_int, as_map, decode_document, need, robot_id, valid_id

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

VERSION = 1  # unsigned slots
SIGNED_VERSION = 2  # owner-signed slots (docs/wire.md, "Signed slots")
# Stacks that hold a per-object slot (docs/wire.md, "Per-object slots"): unsigned, signed. A stack
# of realisation tables only is still written as version 1 or 2, byte for byte.
OBJECTS_VERSION = 3
SIGNED_OBJECTS_VERSION = 4
VERSIONS = (VERSION, SIGNED_VERSION, OBJECTS_VERSION, SIGNED_OBJECTS_VERSION)
_SIGNED_VERSIONS = (SIGNED_VERSION, SIGNED_OBJECTS_VERSION)
STACK = "stack"
_F64 = np.dtype("<f8")
_MAX_STAMP = MAX_STEP  # a stamp is its owner's step
_MAX_OBJECT_ID = 2**32 - 1
_TOP_KEYS = frozenset({"v", "type", "sender", "k", "pos", "slots"})
_SLOT_KEYS = frozenset({"owner", "stamp", "objects", "real"})
_EPOCH_SLOT_KEYS = _SLOT_KEYS | {"epoch"}  # versions 1, 3: "epoch" only when it is not 0
_SIGNED_SLOT_KEYS = _SLOT_KEYS | {"epoch", "sig"}
MAX_EPOCH = 2**53 - 1  # an epoch is a count of milliseconds (docs/wire.md, "Versions and epochs")
# The age a stack says each of its slots has (``age``, docs/wire.md, "Holding times"), at most a
# day in milliseconds: a sender clamps an older one to it.
MAX_AGE_MS = 86_400_000
_AGE_KEY = msgpack.packb("age")
_REAL_KEYS = frozenset({"c", "phi", "lin", "info", "eta"})
# A realisation whose ξ is that of an earlier realisation of the slot (docs/wire.md, "Shared ξ").
_REF_KEYS = frozenset({"c", "phi", "xi"})
# A per-object slot's ``real`` (versions 3 and 4): its kind, the tangent dimension of an object,
# M, the (n, M) class log φ as float32 and the one ξ.
_OBJECTS_KEYS = frozenset({"kind", "dim", "m", "phi", "lin", "info", "eta"})
OBJECTS_KIND = "objects"
# A per-object slot's ``ids`` key: its object ids are the owner's robot-local ones (absent: global)
LOCAL_IDS_VALUE = "local"
OBJECT_DIM = 3  # Pose2 objects: x, y, θ (a realisation table's, always)
# Per-object slots: Pose2 objects (x, y, θ) or Point2 landmarks (x, y)
# (estimator.models.objects); older peers refuse a dimension they do not know, by name.
OBJECT_DIMS = (3, 2)
_F32 = np.dtype("<f4")
# A per-object slot whose ξ is sparse (``"xi": "sparse"``, docs/wire.md, "Sparse ξ"): Λ_s as the
# upper entries of its diagonal blocks, its edges (object pairs) and their blocks, all float32.
SPARSE_XI = "sparse"
_SPARSE_KEYS = frozenset(
    {"kind", "dim", "m", "phi", "lin", "xi", "diag", "edges", "edge_info", "eta"}
)
# Edges per object a sparse ξ may have: a Bayes net with p parents per object has at most
# p(p + 1)/2 moral edges per object: 6 for the default 3 (tree parent + 2 extra), 10 for the
# most a sender may use (tree parent + MAX_XI_PARENTS = 3).
MAX_EDGES_PER_OBJECT = (1 + MAX_XI_PARENTS) * (2 + MAX_XI_PARENTS) // 2
_EDGE_INDEX = np.dtype("<u2")  # an edge's object indices: so a sparse ξ has < 65 536 objects
MAX_SPARSE_OBJECTS = 2**16 - 1
_UPPER3 = np.triu_indices(3)  # a 3 × 3 block's 6 upper entries, row by row
_ONE_XI = np.zeros(1, dtype=np.int64)  # numbers_problem's rows for a per-object slot's one ξ
_NO_PHI = np.zeros(0)  # its log φ are checked apart (class_phi_problem)
_ONE_XI.flags.writeable = _NO_PHI.flags.writeable = False


@dataclass(frozen=True, slots=True)
class Limits:
    """What a receiver accepts, and a sender may send (docs/wire.md, "Limits": principle and
    measured ranges behind every default).

    Counts: ``num_classes`` bounds class indices; bytes, slots, objects per slot, realisations
    per slot. Numbers, absolute: every eigenvalue of Λ in [−``psd_tol``·max|λ|,
    ``max_information``] and κ(Λ) ≤ ``max_condition``, with κ(Λ) = (λmax + f)/(λmin + f) and
    f = 1/``world_extent``² (the information of "somewhere in the world"), infinite when
    λmin + f ≤ 0; |log φ| ≤ ``max_abs_log_phi``; |x|, |y| ≤ ``world_extent`` (metres) for every
    position (``lin``, ``pos``) and |θ| ≤ 2π; ‖η‖₂ ≤ max(λmax, 0)·δmax(n) (:func:`eta_bound`).
    """

    num_classes: int = 64
    max_message_bytes: int = 32 * 1024 * 1024
    max_slots: int = 64
    max_objects: int = 512
    max_realisations: int = 1024
    psd_tol: float = 1e-9
    max_information: float = 1e9
    max_condition: float = 1e12
    max_abs_log_phi: float = 1e6
    world_extent: float = 1e4

    def __post_init__(self) -> None:
        counts = (self.num_classes, self.max_message_bytes, self.max_slots)
        if min(*counts, self.max_objects, self.max_realisations) < 1 or self.num_classes > 256:
            raise ValueError(f"limits: counts must be ≥ 1 and num_classes ≤ 256, got {self}")
        bounds = (self.max_information, self.max_abs_log_phi, self.world_extent)
        if not all(0.0 < b < math.inf for b in bounds) or not 1.0 <= self.max_condition < math.inf:
            raise ValueError(f"limits: bounds must be finite, > 0, max_condition ≥ 1: {self}")
        if not 0.0 <= self.psd_tol < 1.0:
            raise ValueError(f"limits: psd_tol must be in [0, 1), got {self.psd_tol}")


# Angles are accepted in any of the usual wraps, (−π, π] or [0, 2π): anything beyond is not an
# angle a pose estimator produces, and cos/sin of a huge θ has no digits left.
MAX_ABS_THETA = 2.0 * math.pi


def eta_bound(n: int, lim: Limits, d: int = 3) -> float:
    """δmax(n): the longest tangent offset ‖δ‖₂ between two poses (d = 3) or two points
    (d = 2) of n objects in the world.

    η = Λδ, with δ the offset of ξ's mean from ``lin`` (both in the world), so ‖η‖₂ ≤ λmax·‖δ‖₂.
    Per object, ‖t‖₂ ≤ 2√2·W for a translation t in the world box [−W, W]². A point's tangent
    is t: ‖δ_i‖₂² ≤ 8W². A pose's: |δθ| ≤ π, and the Pose2 logarithm maps t to V(θ)⁻¹t with
    ‖V⁻¹‖ ≤ (π/2)/sin(π/2) = π/2 for |θ| ≤ π, so ‖δ_i‖₂² ≤ (π/2)²·8W² + π² = π²(2W² + 1).
    """
    if d == 2:
        return math.sqrt(n * 8.0) * lim.world_extent
    return math.pi * math.sqrt(n * (2.0 * lim.world_extent**2 + 1.0))


@dataclass(frozen=True, slots=True, eq=False)
class StackMessage:
    """A stack as sent by ``sender`` from ``position`` (x, y), for proximity filtering, after the
    sender's step ``step`` (lets a lock-step receiver pick the version of the right round)."""

    sender: str
    position: tuple[float, float] | None
    stack: Stack
    step: int = 0
    # Owners of the slots ``decode`` left out, unparsed (versions the receiver did not want).
    skipped: tuple[str, ...] = ()
    # Delta gossip (docs/wire.md): the sender's digest, owner → (epoch, stamp) of every slot it
    # holds (its own included), when ``slots`` carries only what its peers lack; None in a full
    # stack.
    have: dict[str, tuple[int, int]] | None = None
    # Owners of the slots ``decode`` took, unparsed, from the receiver's ``parsed`` (same bytes).
    reused: tuple[str, ...] = ()
    # Delta gossip in real time (docs/wire.md): owner → relay, the owners whose newer version
    # the sender lacks, does not hear from the owner, and asks that relay for now; only with
    # ``have``. None: no ask.
    ask: dict[str, str] | None = None
    # Holding times (docs/wire.md, "Holding times"): owner → the milliseconds since its owner's
    # step made the slot, summed over the robots that held it on the way, transits excluded,
    # for every slot the message carries (``skipped`` ones included). None: not said.
    age: dict[str, int] | None = None


@functools.lru_cache(maxsize=64)
def _tri(n: int, d: int = 3) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The upper-triangle indices of a dn × dn matrix (cached: only read, never written)."""
    return np.triu_indices(d * n)


@functools.lru_cache(maxsize=64)
def _mirror_index(n: int, d: int = 3) -> NDArray[np.intp]:
    """(dn, dn): the position in the upper triangle (row by row) of every entry of the matrix."""
    iu = _tri(n, d)
    index = np.zeros((d * n, d * n), dtype=np.intp)
    index[iu] = np.arange(len(iu[0]))
    index[iu[1], iu[0]] = np.arange(len(iu[0]))
    index.flags.writeable = False
    return index


def _mirror(upper: Array, n: int, d: int = 3) -> Array:
    """(R, dn, dn) symmetric matrices from their upper triangles (R, dn(dn+1)/2), row by row:
    one gather (each entry a copy of its upper-triangle value, −0.0 included)."""
    return np.take(upper, _mirror_index(n, d), axis=1)


# --------------------------------------------------------------------------- shared rules

# A broken rule: the remote error class decode raises, the field and the message; encode raises
# LocalProtocolError with the same field and message instead.
Problem = tuple[type[RemoteProtocolError], str, str]


def _position_problem(pos: tuple[float, float], lim: Limits) -> Problem | None:
    if not all(math.isfinite(v) for v in pos):
        return InvalidValue, "pos", "non-finite number"
    if max(abs(v) for v in pos) > lim.world_extent:
        return LimitExceeded, "pos", f"{pos} outside ±world_extent = {lim.world_extent:g} m"
    return None


def numbers_problem(
    where: str,
    log_phi: Array,
    lin: Array,
    info: Array,
    eta: Array,
    lim: Limits,
    rows: IntArray | None = None,
) -> Problem | None:
    """The first broken number rule of a slot's realisations, or None; ``where`` is the slot's
    field (``slots[i]``). ``log_phi`` (R,) of every realisation; ``lin`` (X, n, 3), ``info``
    (X, 3n, 3n) symmetric, ``eta`` (X, 3n) of the slot's X distinct ξ, carried by the
    realisations ``rows`` (X,) (default: ξ i by realisation i). Checked field by field over all
    at once, in wire order: φ, lin, Λ, η; one batched Cholesky per slot, and one batched
    ``eigvalsh`` when it cannot decide."""
    rows = np.arange(len(lin)) if rows is None else rows
    # Each rule is first decided on one number for all (the valid case: a slot's decode is a
    # few dozen such checks); only a broken one looks for the realisation at fault.
    largest_phi = float(np.abs(log_phi).max()) if len(log_phi) else 0.0  # NaN if any is NaN
    if not math.isfinite(largest_phi):
        return InvalidValue, _at(where, ~np.isfinite(log_phi), "phi"), "non-finite number"
    x = len(lin)
    for name, arr in (("lin", lin), ("info", info), ("eta", eta)):
        if np.isfinite(arr).all():
            continue
        flagged = ~np.isfinite(arr.reshape(x, -1)).all(axis=1)
        return InvalidValue, _at(where, flagged, name, rows), "non-finite number"
    if not largest_phi <= lim.max_abs_log_phi:
        bad = np.abs(log_phi) > lim.max_abs_log_phi
        value = float(log_phi[np.argmax(bad)])
        return LimitExceeded, _at(where, bad, "phi"), f"|{value:g}| > max_abs_log_phi"
    if info.shape[1] == 0:
        return None
    magnitude = np.abs(lin)
    if float(magnitude[..., :2].max()) > lim.world_extent:
        bad = magnitude[..., :2].max(axis=(1, 2)) > lim.world_extent
        field = _at(where, bad, "lin", rows)
        return LimitExceeded, field, f"a position outside ±{lim.world_extent:g} m"
    if lin.shape[-1] == 3 and float(magnitude[..., 2].max()) > MAX_ABS_THETA:
        bad = magnitude[..., 2].max(axis=1) > MAX_ABS_THETA
        return InvalidValue, _at(where, bad, "lin", rows), "an angle outside ±2π"
    d = lin.shape[-1]
    if _certified(info, eta, lim, d):
        return None
    return _spectral_problem(where, info, eta, lim, rows, d)


def _at(where: str, bad: Any, name: str, rows: IntArray | None = None) -> str:
    """The field of the first realisation flagged in ``bad`` (of the realisation ``rows[i]``
    when ``bad`` flags distinct ξ)."""
    first = int(np.argmax(bad))
    return f"{where}.real[{first if rows is None else int(rows[first])}].{name}"


def _eta_norm(eta: Array) -> Array:
    """‖η‖₂ per row of (R, m), scaled by max|ηᵢ| first: squares of tiny or huge entries would
    under- or overflow (a norm beyond the largest float is inf, without a warning)."""
    scale = np.abs(eta).max(axis=1)
    unit = np.linalg.norm(eta / np.where(scale > 0.0, scale, 1.0)[:, None], axis=1)
    with np.errstate(over="ignore"):
        return np.asarray(scale * unit)


def _certified(info: Array, eta: Array, lim: Limits, d: int = 3) -> bool:
    """True when one batched Cholesky proves every Λ and η rule for all (R, 3n, 3n) ``info``, so
    that no eigendecomposition is needed (the common case; it costs a fifth of ``eigvalsh``).

    G = max row sum of |Λ| bounds every |λ| (Gershgorin) and d = max Λᵢᵢ ≤ λmax (a Rayleigh
    quotient). G ≤ max_information gives λmax's bound; Λ − sI ≻ 0 with s = max((G + f)/K − f, 0)
    gives λmin > s ≥ 0 (so Λ is definite) and κ = (λmax + f)/(λmin + f) < (G + f)/(s + f) ≤ K;
    ‖η‖ ≤ d·δmax gives η's. Otherwise (semidefinite, ill-conditioned or invalid Λ) it is False
    and the eigenvalues decide.
    """
    if len(info) == 1:
        return _certified_one(info[0], eta[0], lim, d)
    with np.errstate(over="ignore"):  # inf fails the bound below
        gershgorin = np.abs(info).sum(axis=2).max(axis=1)
    if not (gershgorin <= lim.max_information).all():
        return False
    largest_diagonal = np.diagonal(info, axis1=1, axis2=2).max(axis=1)
    reach = largest_diagonal * eta_bound(info.shape[1] // d, lim, d)
    # ‖η‖ ≤ √m·max|ηᵢ|: that bound decides most slots without the norm itself (an overflow to
    # inf fails it, and the scaled norm decides)
    with np.errstate(over="ignore"):
        quick = (math.sqrt(eta.shape[1]) * np.abs(eta).max(axis=1) <= reach).all()
    if not quick and not (_eta_norm(eta) <= reach).all():
        return False
    floor = lim.world_extent**-2
    shift = np.maximum((gershgorin + floor) / lim.max_condition - floor, 0.0)
    try:
        np.linalg.cholesky(info - shift[:, None, None] * np.eye(info.shape[1]))
    except np.linalg.LinAlgError:
        return False
    return True


def _certified_one(info: Array, eta: Array, lim: Limits, d: int = 3) -> bool:
    """:func:`_certified` for one (3n, 3n) Λ and its η (a slot's realisations nearly always share
    one ξ): the same bounds in floats, and LAPACK's Cholesky called directly. For a single
    matrix the batched form took a third of a paper stack's decode (0.12 of 0.38 ms), this one
    half as long."""
    magnitude = np.abs(info)
    # Every |Λᵢⱼ| ≤ G: beyond the bound, G is too; within it, a row sum of 3n of them cannot
    # overflow (no floating-point error state to set up).
    if not float(magnitude.max()) <= lim.max_information:
        return False
    gershgorin = float(magnitude.sum(axis=1).max())
    if not gershgorin <= lim.max_information:
        return False
    reach = float(info.diagonal().max()) * eta_bound(len(info) // d, lim, d)
    if (
        not math.sqrt(len(eta)) * float(np.abs(eta).max()) <= reach
        and not float(_eta_norm(eta[None])[0]) <= reach
    ):
        return False
    floor = lim.world_extent**-2
    shifted = info.copy()
    shifted.flat[:: len(info) + 1] -= max((gershgorin + floor) / lim.max_condition - floor, 0.0)
    _, failed = dpotrf(shifted, lower=1, clean=0, overwrite_a=1)
    return bool(failed == 0)


def _spectral_problem(
    where: str, info: Array, eta: Array, lim: Limits, rows: IntArray, d: int = 3
) -> Problem | None:
    """The first broken Λ or η rule, decided by Λ's extreme eigenvalues (one batched
    ``eigvalsh``)."""
    # Every test is written "not within": a NaN that eigvalsh may return for matrices near the
    # float64 range fails it, as does inf.
    lam = np.linalg.eigvalsh(info)
    lo, hi = lam[:, 0], lam[:, -1]
    bad = ~(hi <= lim.max_information)
    if bad.any():
        value = float(hi[np.argmax(bad)])
        return LimitExceeded, _at(where, bad, "info", rows), f"λmax = {value:.3g} > max_information"
    bad = ~(lo >= -lim.psd_tol * np.maximum(hi, -lo))
    if bad.any():
        return (
            InvalidValue,
            _at(where, bad, "info", rows),
            f"Λ is indefinite (λmin = {lo[np.argmax(bad)]:.3g})",
        )
    floor = lim.world_extent**-2
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = np.where(lo + floor > 0.0, (hi + floor) / (lo + floor), np.inf)
    bad = ~(kappa <= lim.max_condition)
    if bad.any():
        value = float(kappa[np.argmax(bad)])
        return (
            LimitExceeded,
            _at(where, bad, "info", rows),
            f"condition number {value:.3g} > max_condition",
        )
    bad = ~(_eta_norm(eta) <= np.maximum(hi, 0.0) * eta_bound(info.shape[1] // d, lim, d))
    if bad.any():
        return (
            LimitExceeded,
            _at(where, bad, "eta", rows),
            "‖η‖ > λmax·δmax: ξ's mean lies outside the world",
        )
    return None


def class_phi_problem(where: str, log_phi: Array, lim: Limits) -> Problem | None:
    """The first broken rule of a per-object slot's (n, M) class log φ as it travels (float32
    values, as float64), or None; ``where`` is the slot's field (``slots[i]``). Every value
    finite and |log φ| ≤ ``max_abs_log_phi``, as a table slot's log φ."""
    field = f"{where}.real.phi"
    largest = float(np.abs(log_phi).max()) if log_phi.size else 0.0  # NaN if any is NaN
    if math.isfinite(largest) and largest <= lim.max_abs_log_phi:
        return None
    if not math.isfinite(largest):
        j, c = np.argwhere(~np.isfinite(log_phi))[0]
        return InvalidValue, field, f"non-finite number (objects[{j}], class {c})"
    j, c = np.argwhere(np.abs(log_phi) > lim.max_abs_log_phi)[0]
    value = float(log_phi[j, c])
    return LimitExceeded, field, f"|{value:.9g}| > max_abs_log_phi (objects[{j}], class {c})"


def object_xi_problem(
    where: str, lin: Array, info: Array, eta: Array, lim: Limits
) -> Problem | None:
    """:func:`numbers_problem` for a per-object slot's one ξ (``lin`` (n, 3), ``info`` (3n, 3n)
    symmetric, ``eta`` (3n,)): the same rules, the fields named ``slots[i].real.lin`` etc."""
    problem = numbers_problem(where, _NO_PHI, lin[None], info[None], eta[None], lim, _ONE_XI)
    if problem is None:
        return None
    error, field, message = problem
    table = f"{where}.real[0]."  # numbers_problem names ξ 0 as a table's realisation 0
    assert field.startswith(table), field
    return error, f"{where}.real.{field[len(table) :]}", message


# --------------------------------------------------------------------------- encode


def encode(message: StackMessage, limits: Limits | None = None) -> bytes:
    """Bytes of a stack message. Raises :class:`LocalProtocolError`, naming the field as decode
    would, for anything ``decode`` would reject under the same ``limits``: sending it would only
    make every receiver count an error."""
    lim = limits or Limits()
    if not valid_id(message.sender):
        raise LocalProtocolError(f"invalid robot id {message.sender!r}", "sender")
    pos = None
    if message.position is not None:
        try:
            pos = [float(v) for v in message.position]
        except (TypeError, ValueError):
            raise LocalProtocolError("must be two numbers", "pos") from None
        _local(len(pos) == 2, "pos", "must be two numbers")
        _raise_local(_position_problem((pos[0], pos[1]), lim))
    step = message.step
    _local(
        isinstance(step, int) and not isinstance(step, bool) and 0 <= step <= _MAX_STAMP,
        "k",
        f"step must be an integer in 0..{_MAX_STAMP}, got {step!r}",
    )
    slots = message.stack.slots
    _local(len(slots) <= lim.max_slots, "slots", f"{len(slots)} > {lim.max_slots}")
    signed = {s.signature is not None for s in slots}
    _local(len(signed) <= 1, "slots", "signed and unsigned slots in one stack")
    head: dict[str, Any] = {
        "v": _version(signed == {True}, any(_per_object(s) for s in slots)),
        "type": STACK,
        "sender": message.sender,
        "k": step,
        "pos": pos,
    }
    have: list[list[Any]] | None = None
    if message.have is not None:
        entries = sorted(message.have.items())
        _local(len(entries) <= lim.max_slots, "have", f"{len(entries)} > {lim.max_slots}")
        for o, (e, k) in entries:
            ok = valid_id(o) and 0 <= e <= MAX_EPOCH and 0 <= k <= _MAX_STAMP
            _local(ok, "have", f"invalid entry {[o, e, k]!r}")
        have = [[o, int(e), int(k)] for o, (e, k) in entries]
    ask: list[list[str]] | None = None
    if message.ask is not None:
        _local(have is not None, "ask", "an ask goes only with a digest (have)")
        pairs = sorted(message.ask.items())
        _local(len(pairs) <= lim.max_slots, "ask", f"{len(pairs)} > {lim.max_slots}")
        for o, r in pairs:
            _local(valid_id(o) and valid_id(r), "ask", f"invalid entry {[o, r]!r}")
        ask = [[o, r] for o, r in pairs]
    # What msgpack.packb of the whole map would write, with each slot's bytes spliced in: a
    # slot that carries its wire form (received and validated, or made once) is not re-encoded.
    packer = msgpack.Packer(use_bin_type=True)
    parts = [packer.pack_map_header(len(head) + 1)]
    for key, value in head.items():
        parts += [packer.pack(key), packer.pack(value)]
    ages = _ages_local(message.age, slots)
    optional = (have is not None) + (ask is not None) + (ages is not None)
    parts[0] = packer.pack_map_header(len(head) + 1 + optional)
    parts += [packer.pack("slots"), packer.pack_array_header(len(slots))]
    parts += [_slot_bytes(s, f"slots[{i}]", lim, packer) for i, s in enumerate(slots)]
    if have is not None:
        parts += [packer.pack("have"), packer.pack(have)]
    if ask is not None:
        parts += [packer.pack("ask"), packer.pack(ask)]
    if ages is not None:  # last, so that ``stamp_ages`` can rewrite it at the moment of sending
        parts += [_AGE_KEY, packer.pack(ages)]
    blob = b"".join(parts)
    # Room for ``stamp_ages``: every age may grow from one byte to five (a uint32).
    size_ok = len(blob) + 4 * len(ages or ()) <= lim.max_message_bytes
    _local(size_ok, "message", f"{len(blob)} bytes > {lim.max_message_bytes}")
    return blob


def _ages_local(age: dict[str, int] | None, slots: tuple[Slot, ...]) -> list[int] | None:
    """The ``age`` array of a message carrying ``slots``: one age per slot, in their order."""
    if age is None:
        return None
    out = []
    for i, slot in enumerate(slots):
        value = age.get(slot.owner)
        ok = _is_int(value) and 0 <= int(value) <= MAX_AGE_MS  # type: ignore[arg-type]
        _local(ok, f"age[{i}]", f"expected an integer in 0..{MAX_AGE_MS} for {slot.owner!r}")
        out.append(int(value))  # type: ignore[arg-type]
    _local(len(age) == len(slots), "age", f"{len(age)} ages for {len(slots)} slots")
    return out


def stamp_ages(data: bytes, ages: list[int]) -> bytes | None:
    """``data``, a message ``encode`` wrote with every age 0 and ``len(ages)`` slots, with
    ``ages`` (clamped to 0 … ``MAX_AGE_MS``) in their place: the holding times as they are when
    the message is sent, not when it was made. None when ``data`` does not end in such an
    ``age`` (e.g. its own slot was left out: docs/wire.md, "Holding times")."""
    tail = _AGE_KEY + msgpack.packb([0] * len(ages))
    if not data.endswith(tail):
        return None
    clamped = [min(max(int(a), 0), MAX_AGE_MS) for a in ages]
    return data[: len(data) - len(tail)] + _AGE_KEY + msgpack.packb(clamped)


def _local(cond: bool, field: str, message: str) -> None:
    if not cond:
        raise LocalProtocolError(message, field)


def _raise_local(problem: Problem | None) -> None:
    if problem is not None:
        raise LocalProtocolError(problem[2], problem[1])


def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _per_object(slot: Slot) -> bool:
    return slot.summary.per_object is not None


def _version(signed: bool, objects: bool) -> int:
    """The wire version of a stack: 1 or 2 (signed) for realisation tables only, 3 or 4 once
    any slot is per object."""
    if objects:
        return SIGNED_OBJECTS_VERSION if signed else OBJECTS_VERSION
    return SIGNED_VERSION if signed else VERSION


def _slot_bytes(slot: Slot, where: str, lim: Limits, packer: msgpack.Packer) -> bytes:
    if slot.wire is not None and slot.wire.fits(slot):
        return slot.wire.data
    return bytes(packer.pack(_encode_slot(slot, where, lim)))


def with_wire(slot: Slot, limits: Limits | None = None) -> Slot:
    """``slot`` with its bytes made once (:class:`LocalProtocolError` if the limits refuse
    it): every stack that carries it then splices them in instead of encoding it again."""
    data = bytes(msgpack.packb(_encode_slot(slot, "slot", limits or Limits()), use_bin_type=True))
    wire = WireForm(slot.owner, slot.epoch, slot.stamp, slot.signature, slot.summary, data)
    return dataclasses.replace(slot, wire=wire)


def _encode_slot(slot: Slot, where: str, lim: Limits) -> dict[str, Any]:
    _local(valid_id(slot.owner), f"{where}.owner", f"invalid robot id {slot.owner!r}")
    stamp_ok = _is_int(slot.stamp) and 0 <= slot.stamp <= _MAX_STAMP
    _local(stamp_ok, f"{where}.stamp", f"{slot.stamp!r} outside 0..{_MAX_STAMP}")
    raw_ids = slot.summary.object_ids
    n = len(raw_ids)
    _local(n <= lim.max_objects, f"{where}.objects", f"{n} > {lim.max_objects}")
    ids_ok = all(_is_int(j) and 0 <= j <= _MAX_OBJECT_ID for j in raw_ids)
    _local(ids_ok, f"{where}.objects", "ids must be integers in 0..2³²−1")
    ids = [int(j) for j in raw_ids]
    _local(len(set(ids)) == n, f"{where}.objects", "duplicate object ids")
    real: dict[str, Any] | list[dict[str, Any]]
    if slot.summary.per_object is not None:
        real = _encode_objects(slot.summary, where, n, lim)
    else:
        real = _encode_table(slot.summary, where, n, lim)
    out: dict[str, Any] = {"owner": slot.owner, "stamp": int(slot.stamp), "objects": ids}
    out["real"] = real
    epoch = slot.epoch
    epoch_ok = isinstance(epoch, int) and not isinstance(epoch, bool) and 0 <= epoch <= MAX_EPOCH
    _local(epoch_ok, f"{where}.epoch", f"must be an integer in 0..{MAX_EPOCH}, got {epoch!r}")
    if epoch or slot.signature is not None:
        out["epoch"] = int(epoch)
    if slot.signature is not None:
        sig_ok = isinstance(slot.signature, bytes) and len(slot.signature) == SIGNATURE_BYTES
        _local(sig_ok, f"{where}.sig", f"expected {SIGNATURE_BYTES} bytes")
        out["sig"] = slot.signature
    return out


def _encode_table(summary: LocalSummary, where: str, n: int, lim: Limits) -> list[dict[str, Any]]:
    """A realisation table's ``real``: one map per realisation (docs/wire.md, "Message")."""
    rs = summary.realisations
    _local(len(rs) >= 1, f"{where}.real", "no realisation")
    _local(len(rs) <= lim.max_realisations, f"{where}.real", f"{len(rs)} > {lim.max_realisations}")
    xis, which = summary.distinct_xi()
    carrier: dict[int, int] = {}  # ξ → the realisation that carries it on the wire (its first)
    for i, x in enumerate(which):
        carrier.setdefault(x, i)
    rows = np.array([carrier[x] for x in range(len(xis))], dtype=np.int64)
    for i, r in enumerate(rs):
        field = f"{where}.real[{i}]"
        if rows[which[i]] == i:
            shapes = (
                np.shape(r.xi.lin) == (n, 3)
                and np.shape(r.xi.info) == (3 * n, 3 * n)
                and np.shape(r.xi.eta) == (3 * n,)
            )
            _local(shapes, field, "shapes do not match the object count")
        _local(len(r.classes) == n, f"{field}.c", f"expected {n} classes")
        phi_ok = isinstance(r.log_phi, float | int | np.floating | np.integer)
        _local(
            phi_ok and not isinstance(r.log_phi, bool | np.bool_),
            f"{field}.phi",
            "expected a number",
        )
    classes = np.array([r.classes for r in rs]).reshape(len(rs), n)
    if n:
        _local(classes.dtype.kind in "iu", f"{where}.real", "classes must be integers")
        bad_rows = ((classes < 0) | (classes >= lim.num_classes)).any(axis=1)
        _local(
            not bad_rows.any(),
            f"{where}.real[{int(np.argmax(bad_rows))}].c",
            f"classes must be in 0..{lim.num_classes - 1}",
        )
    # One array per field for the whole slot: the checks and conversions run once per distinct
    # ξ, not per realisation.
    phi = np.array([float(r.log_phi) for r in rs])
    lin = np.ascontiguousarray(np.stack([x.lin for x in xis]), dtype=_F64)
    info = np.ascontiguousarray(np.stack([x.info for x in xis]), dtype=_F64)
    eta = np.ascontiguousarray(np.stack([x.eta for x in xis]), dtype=_F64)
    iu = _tri(n)
    upper = info[:, iu[0], iu[1]]
    sent = _mirror(upper, n)  # what decode rebuilds: validate exactly that
    if n:
        with np.errstate(over="ignore", invalid="ignore"):  # inf or nan fail the test below
            scale = np.abs(info).max(axis=(1, 2))
            asymmetry = np.abs(info - info.transpose(0, 2, 1)).max(axis=(1, 2))
            bad_rows = ~(asymmetry <= 1e-12 * scale)
        # A non-finite number that is sent is reported as such, in wire order, below.
        bad_rows &= np.isfinite(sent).all(axis=(1, 2))
        _local(
            not bad_rows.any(),
            f"{where}.real[{int(rows[np.argmax(bad_rows)])}].info",
            "Λ not symmetric (or not finite below its diagonal)",
        )
    _raise_local(numbers_problem(where, phi, lin, sent, eta, lim, rows))
    reals: list[dict[str, Any]] = []
    for i, r in enumerate(rs):
        head = {"c": classes[i].astype(np.uint8).tobytes(), "phi": float(r.log_phi)}
        g = which[i]
        if rows[g] == i:
            head |= {"lin": lin[g].tobytes(), "info": upper[g].tobytes(), "eta": eta[g].tobytes()}
        else:
            head["xi"] = int(rows[g])
        reals.append(head)
    return reals


def _encode_objects(summary: LocalSummary, where: str, n: int, lim: Limits) -> dict[str, Any]:
    """A per-object slot's ``real`` (docs/wire.md, "Per-object slots"): refuses, naming the
    field as decode would, what a receiver refuses — checked on the values as they travel
    (log φ rounded to float32, Λ's upper triangle mirrored)."""
    field = f"{where}.real"
    po = summary.per_object
    assert po is not None
    _local(len(summary.realisations) == 0, field, "a per-object summary has no realisations")
    raw_phi = np.asarray(po.log_phi)
    _local(
        raw_phi.ndim == 2 and raw_phi.shape[0] == n,
        f"{field}.phi",
        f"expected (n, M) = ({n}, M) class log φ, got shape {raw_phi.shape}",
    )
    _local(raw_phi.dtype.kind in "fiu", f"{field}.phi", f"expected numbers, got {raw_phi.dtype}")
    m = raw_phi.shape[1]
    _local(1 <= m <= lim.num_classes, f"{field}.m", f"{m} outside 1..{lim.num_classes}")
    xi = po.xi
    d = int(np.shape(xi.lin)[1]) if np.ndim(xi.lin) == 2 else -1
    _local(
        d in OBJECT_DIMS, f"{field}.dim", f"objects of dimension {d} (known: 3, Pose2; 2, Point2)"
    )
    if not isinstance(xi, Xi):  # the other form: a SparseXi
        shapes = _sparse_shapes(xi, n, d)
    else:
        shapes = (
            np.shape(xi.lin) == (n, d)
            and np.shape(xi.info) == (d * n, d * n)
            and np.shape(xi.eta) == (d * n,)
        )
    _local(shapes, field, "ξ's shapes do not match the object count")
    phi = raw_phi.astype(np.float64)
    _raise_local(class_phi_problem(where, phi, lim))  # as given: the value the sender meant
    with np.errstate(over="ignore"):  # beyond float32 is inf, refused as over the bound below
        phi32 = phi.astype(_F32)
    _raise_local(class_phi_problem(where, phi32.astype(np.float64), lim))  # as it travels
    ids = {"ids": LOCAL_IDS_VALUE} if po.local_ids else {}  # given ids: the bytes of before
    if not isinstance(xi, Xi):
        head = {"kind": OBJECTS_KIND, "dim": d, "m": int(m), "phi": phi32.tobytes()}
        return head | _encode_sparse(xi, where, n, lim) | ids
    lin = np.ascontiguousarray(xi.lin, dtype=_F64)
    info = np.ascontiguousarray(xi.info, dtype=_F64)
    eta = np.ascontiguousarray(xi.eta, dtype=_F64)
    iu = _tri(n, d)
    upper = info[iu]
    sent = _mirror(upper[None], n, d)[0]  # what decode rebuilds: validate exactly that
    if n:
        with np.errstate(over="ignore", invalid="ignore"):  # inf or nan fail the test below
            symmetric = bool(np.abs(info - info.T).max() <= 1e-12 * np.abs(info).max())
        # A non-finite number that is sent is reported as such, in wire order, below.
        _local(
            symmetric or not np.isfinite(sent).all(),
            f"{field}.info",
            "Λ not symmetric (or not finite below its diagonal)",
        )
    _raise_local(object_xi_problem(where, lin, sent, eta, lim))
    return {
        "kind": OBJECTS_KIND,
        "dim": d,
        "m": int(m),
        "phi": phi32.tobytes(),
        "lin": lin.tobytes(),
        "info": upper.tobytes(),
        "eta": eta.tobytes(),
    } | ids


def _sparse_shapes(xi: SparseXi, n: int, d: int) -> bool:
    """Whether a sparse ξ's arrays are numbers of the shapes n objects of dimension d need:
    ``lin`` (n, d), ``diag_info`` (n, d, d), ``edges`` (E, 2) integers, ``edge_info`` (E, d, d),
    ``eta`` (dn,)."""
    arrays = [np.asarray(a) for a in (xi.lin, xi.diag_info, xi.edges, xi.edge_info, xi.eta)]
    lin, diag, edges, edge_info, eta = arrays
    e = len(edges) if edges.ndim == 2 else -1
    return (
        all(a.dtype.kind in "fiu" for a in arrays)
        and (edges.dtype.kind in "iu" or edges.size == 0)
        and lin.shape == (n, d)
        and diag.shape == (n, d, d)
        and edges.shape == (e, 2)
        and edge_info.shape == (e, d, d)
        and eta.shape == (d * n,)
    )


def _encode_sparse(xi: SparseXi, where: str, n: int, lim: Limits) -> dict[str, Any]:
    """A sparse ξ's part of a per-object ``real`` (docs/wire.md, "Sparse ξ"), checked as it
    travels. Only the sender can break two rules: the values must already be float32
    (``SparseXi.float32`` rounds them so that Λ_s stays under the owner's Λ; rounding them here
    to nearest would not), and the diagonal blocks symmetric (their upper entries travel)."""
    field = f"{where}.real"
    lin = np.ascontiguousarray(xi.lin, dtype=_F64)
    diag = np.asarray(xi.diag_info, dtype=np.float64)
    edges = np.asarray(xi.edges).astype(np.int64).reshape(-1, 2)
    edge_info = np.asarray(xi.edge_info, dtype=np.float64)
    eta = np.ascontiguousarray(xi.eta, dtype=_F64)
    for name, a in (("diag", diag), ("edge_info", edge_info), ("eta", eta)):
        with np.errstate(over="ignore", invalid="ignore"):
            exact = np.array_equal(a.astype(_F32).astype(np.float64), a, equal_nan=True)
        _local(exact, f"{field}.{name}", "not float32 values (round them with SparseXi.float32)")
    upper = np.triu_indices(diag.shape[-1])
    sent = _mirror3(diag[:, upper[0], upper[1]])  # what decode rebuilds: validate that
    if n:
        with np.errstate(over="ignore", invalid="ignore"):
            asymmetry = np.abs(diag - diag.transpose(0, 2, 1)).max()
            symmetric = bool(asymmetry <= 1e-12 * np.abs(diag).max())
        _local(
            symmetric or not np.isfinite(sent).all(),
            f"{field}.diag",
            "a diagonal block of Λ_s is not symmetric (or not finite below its diagonal)",
        )
    _raise_local(sparse_edges_problem(where, edges, n))
    _raise_local(sparse_xi_problem(where, lin, sent, edges, edge_info, eta, lim))
    return {
        "lin": lin.tobytes(),
        "xi": SPARSE_XI,
        "diag": diag[:, upper[0], upper[1]].astype(_F32).tobytes(),
        "edges": edges.astype(_EDGE_INDEX).tobytes(),
        "edge_info": edge_info.astype(_F32).tobytes(),
        "eta": eta.astype(_F32).tobytes(),
    }


def _mirror3(upper: Array) -> Array:
    """(n, d, d) symmetric blocks from their d(d+1)/2 upper entries (n, 6 or 3), row by row."""
    d = 3 if upper.shape[-1] == 6 else 2
    iu = _UPPER3 if d == 3 else np.triu_indices(2)
    blocks = np.empty((len(upper), d, d))
    blocks[:, iu[0], iu[1]] = upper
    blocks[:, iu[1], iu[0]] = upper
    return blocks


def sparse_edges_problem(where: str, edges: IntArray, n: int) -> Problem | None:
    """The first broken rule of a sparse ξ's (E, 2) ``edges`` over n objects, or None: n within
    the uint16 indices and at most ``MAX_EDGES_PER_OBJECT``·n edges (``LimitExceeded``), each a
    pair i < j < n, sorted and each once (``InvalidValue``): the receiver adds each edge's block
    once, to those objects."""
    field = f"{where}.real.edges"
    e = len(edges)
    if n > MAX_SPARSE_OBJECTS:
        return LimitExceeded, field, f"uint16 object indices: {n} > {MAX_SPARSE_OBJECTS} objects"
    if e > MAX_EDGES_PER_OBJECT * n:
        return LimitExceeded, field, f"{e} edges > {MAX_EDGES_PER_OBJECT} per object ({n})"
    if e == 0:
        return None
    i, j = edges[:, 0], edges[:, 1]
    bad = (i < 0) | (i >= j) | (j >= n)
    if bad.any():
        k = int(np.argmax(bad))
        return InvalidValue, field, f"edges[{k}] = ({i[k]}, {j[k]}) is not a pair i < j < {n}"
    key = i * n + j
    bad = key[1:] <= key[:-1]
    if bad.any():
        k = int(np.argmax(bad)) + 1
        return (
            InvalidValue,
            field,
            f"edges[{k}] = ({i[k]}, {j[k]}) does not follow edges[{k - 1}] = "
            f"({i[k - 1]}, {j[k - 1]}): edges are sorted, each once",
        )
    return None


def _sparse_info(diag: Array, edges: IntArray, edge_info: Array) -> Array:
    """Λ_s (dn, dn) from its diagonal blocks (n, d, d), edges (E, 2) and their blocks (E, d, d),
    as ``SparseXi.dense`` builds it (here without importing it: it would load GTSAM)."""
    n, d = len(diag), diag.shape[-1]
    info = np.zeros((n, n, d, d))
    idx = np.arange(n)
    info[idx, idx] = diag
    i, j = edges[:, 0], edges[:, 1]
    info[i, j] = edge_info
    info[j, i] = edge_info.swapaxes(1, 2)
    return info.transpose(0, 2, 1, 3).reshape(d * n, d * n)


def _blocks_problem(field: str, diag: Array, lim: Limits) -> Problem | None:
    """The rules of Λ that Λ_s's block diagonal alone breaks (its eigenvalues are its blocks'):
    λmax, semidefinite, κ, as :func:`_spectral_problem` words them, and positive definite."""
    lam = np.linalg.eigvalsh(diag)
    lo, hi = float(lam[:, 0].min()), float(lam[:, -1].max())
    if not hi <= lim.max_information:
        return LimitExceeded, field, f"λmax = {hi:.3g} > max_information"
    if not lo >= -lim.psd_tol * max(hi, -lo):
        return InvalidValue, field, f"Λ is indefinite (λmin = {lo:.3g})"
    floor = lim.world_extent**-2
    kappa = (hi + floor) / (lo + floor) if lo + floor > 0.0 else math.inf
    if not kappa <= lim.max_condition:
        return LimitExceeded, field, f"condition number {kappa:.3g} > max_condition"
    if not lo > 0.0:
        return InvalidValue, field, "a diagonal block of Λ_s is not positive definite"
    return None


def sparse_xi_problem(
    where: str,
    lin: Array,
    diag: Array,
    edges: IntArray,
    edge_info: Array,
    eta: Array,
    lim: Limits,
) -> Problem | None:
    """:func:`object_xi_problem` for a sparse ξ (``lin`` (n, 3), ``diag`` (n, 3, 3) symmetric,
    valid ``edges`` (E, 2), ``edge_info`` (E, 3, 3), ``eta`` (3n,)), whose Λ_s is also positive
    definite: every number finite, in wire order; then the rules of a dense ξ on Λ_s. A rule of
    Λ that the diagonal blocks alone break (a compression of Λ_s: their λmax, λmin and κ are
    within Λ_s's) names ``diag``; one that only the whole Λ_s breaks names ``edge_info``."""
    field = f"{where}.real"
    for name, a in (("lin", lin), ("diag", diag), ("edge_info", edge_info), ("eta", eta)):
        if not np.isfinite(a).all():
            return InvalidValue, f"{field}.{name}", "non-finite number"
    n = len(lin)
    if n == 0:
        return None
    magnitude = np.abs(lin)  # the rules of numbers_problem, in its words
    if float(magnitude[:, :2].max()) > lim.world_extent:
        return LimitExceeded, f"{field}.lin", f"a position outside ±{lim.world_extent:g} m"
    if lin.shape[1] == 3 and float(magnitude[:, 2].max()) > MAX_ABS_THETA:
        return InvalidValue, f"{field}.lin", "an angle outside ±2π"
    problem = _blocks_problem(f"{field}.diag", diag, lim)
    if problem is not None:
        return problem
    info = _sparse_info(diag, edges, edge_info)
    problem = object_xi_problem(where, lin, info, eta, lim)
    if problem is not None:
        error, name, message = problem
        return error, name.replace(f"{field}.info", f"{field}.edge_info"), message
    _, failed = dpotrf(info, lower=1, clean=0, overwrite_a=1)
    if failed:
        return InvalidValue, f"{field}.edge_info", "Λ_s is not positive definite"
    return None


def sign_slot(slot: Slot, key: Ed25519PrivateKey, limits: Limits | None = None) -> Slot:
    """``slot`` signed by its owner's ``key`` (wire version 2, or 4 for a per-object slot).
    Raises LocalProtocolError, as ``encode`` would, for a slot the limits refuse."""
    unsigned = Slot(slot.owner, slot.stamp, slot.summary, slot.epoch)
    wire = _encode_slot(unsigned, "slot", limits or Limits())
    # The bodies are packed once: hashed as they are (the canonical bytes' digest, as a receiver
    # computes it) and spliced into the slot map, written as _encode_slot's signed slot would be.
    packer = msgpack.Packer(use_bin_type=True)
    objects, real = packer.pack(wire["objects"]), packer.pack(wire["real"])
    found = digest_of_parts(slot.owner, slot.epoch, wire["stamp"], objects, real)
    signature = key.sign(found)
    head = [packer.pack_map_header(6)]
    head += [packer.pack(v) for v in ("owner", slot.owner, "stamp", wire["stamp"], "objects")]
    tail = [packer.pack(v) for v in ("epoch", slot.epoch, "sig", signature)]
    packed = b"".join([*head, objects, packer.pack("real"), real, *tail])
    form = WireForm(slot.owner, slot.epoch, slot.stamp, signature, slot.summary, packed)
    return Slot(slot.owner, slot.stamp, slot.summary, slot.epoch, signature, form)


# --------------------------------------------------------------------------- decode


Wanted = Callable[[str, int, int], bool]  # (owner, epoch, stamp) → parse this slot?
# (owner, epoch, stamp) → a slot of that version this side parsed before, or None
Parsed = Callable[[str, int, int], Slot | None]


def decode(
    data: bytes,
    limits: Limits | None = None,
    keys: SigningKeys | None = None,
    wanted: Wanted | None = None,
    parsed: Parsed | None = None,
) -> StackMessage:
    """Parse and validate a stack message. Raises only :class:`RemoteProtocolError` subclasses.

    ``keys`` (owner → Ed25519 public key): the fleet signs its slots, and every slot must be
    signed by its owner's key (:class:`BadSignature` otherwise: unsigned, unknown owner, or a
    signature that does not verify). Without ``keys`` signatures are kept, not checked.

    ``wanted(owner, epoch, stamp)``: a slot it refuses — a version the receiver already holds or
    has passed — is left out after its header (and, with ``keys``, its signature) is checked:
    its body is neither parsed nor validated (``StackMessage.skipped`` lists it). Every slot
    that is returned carries its bytes as received (``Slot.wire``): a relay re-sends them
    untouched.

    ``parsed(owner, epoch, stamp)``: a slot of this version that the receiver decoded before and
    still keeps (a lock-step agent buffers the stacks of later rounds, and every copy of one
    comes back): when its bytes equal the ones received, that very slot is returned instead of
    parsing the body again (``StackMessage.reused`` lists it)."""
    lim = limits or Limits()
    if (
        isinstance(data, bytearray | memoryview)
        and memoryview(data).nbytes <= lim.max_message_bytes
    ):
        data = bytes(data)

    def parse(doc: Any) -> StackMessage:
        return _decode_doc(doc, lim, keys, (wanted, parsed), data)

    return decode_document(data, lim.max_message_bytes, parse, unpack=scan)


def _floats(blobs: list[Any], where: str, name: str, count: int, rows: IntArray) -> Array:
    """The float64 blobs ``name`` of the realisations ``rows`` of a slot (those that carry their
    ξ) as one (X, count) array."""
    size = 8 * count
    if not all(type(value) is bytes and len(value) == size for value in blobs):  # which, and why
        for i, value in zip(rows, blobs, strict=True):
            field = f"{where}[{i}].{name}"
            need(isinstance(value, bytes), field, "expected binary float64 data")
            need(len(value) == size, field, f"expected {size} bytes, got {len(value)}")
    return np.frombuffer(b"".join(blobs), dtype=_F64).astype(float).reshape(len(blobs), count)


def _decode_doc(
    doc: Any,
    lim: Limits,
    keys: SigningKeys | None,
    hooks: tuple[Wanted | None, Parsed | None],
    buf: bytes,
) -> StackMessage:
    need(isinstance(doc, dict), "message", f"expected a map, got {type(doc).__name__}")
    version = doc.get("v")
    if "v" in doc and (type(version) is not int or version not in VERSIONS):
        speaks = ", ".join(map(str, VERSIONS[:-1])) + f" and {VERSIONS[-1]}"
        raise UnsupportedVersion(f"schema version {doc['v']!r} (this side speaks {speaks})", "v")
    top = as_map(doc, "message", _TOP_KEYS | ({"have", "ask", "age"} & doc.keys()))
    if top["type"] != STACK:
        raise UnsupportedVersion(f"message type {top['type']!r}", "type")
    sender = robot_id(top["sender"], "sender")
    step = as_int(top["k"], "k", 0, _MAX_STAMP)
    position = None
    if top["pos"] is not None:
        pos = top["pos"]
        need(isinstance(pos, list) and len(pos) == 2, "pos", "expected [x, y] or nil")
        need(
            all(isinstance(v, float | int) and not isinstance(v, bool) for v in pos),
            "pos",
            "expected numbers",
        )
        position = (float(pos[0]), float(pos[1]))
        _raise_remote(_position_problem(position, lim))
    raw_slots = top["slots"]
    need(isinstance(raw_slots, list), "slots", "expected an array")
    need(
        len(raw_slots) <= lim.max_slots,
        "slots",
        f"{len(raw_slots)} > {lim.max_slots}",
        LimitExceeded,
    )
    signed = version in _SIGNED_VERSIONS
    if keys is not None and not signed and raw_slots:
        raise BadSignature(
            f"unsigned slots (wire version {version}): this fleet signs its slots", "v"
        )
    maps = version in (OBJECTS_VERSION, SIGNED_OBJECTS_VERSION)  # per-object slots allowed
    headers = [_slot_header(raw, f"slots[{i}]", signed) for i, raw in enumerate(raw_slots)]
    if signed and keys is not None:
        # Every signature before any body: a message that carries one forged slot is refused
        # whole, before a number is read; and the verifications run back to back, each one
        # with the verifier's tables still in cache (interleaved with the parsing of bodies,
        # they took a third longer, docs/wire.md).
        for i, header in enumerate(headers):
            _verify(header, f"slots[{i}]", keys, buf)
    slots, owners, reused = [], [], []
    for i, header in enumerate(headers):
        owner, slot, again = _decode_slot(header, f"slots[{i}]", lim, hooks, buf, maps)
        owners.append(owner)
        if slot is not None:
            slots.append(slot)
        if again:
            reused.append(owner)
    need(len(set(owners)) == len(owners), "slots", f"duplicate owners {owners}", InvalidValue)
    skipped = tuple(o for o in owners if o not in {s.owner for s in slots})
    have = _decode_have(top["have"], lim) if "have" in top else None
    ask = None
    if "ask" in top:
        need(have is not None, "ask", "an ask goes only with a digest (have)")
        ask = _decode_ask(top["ask"], lim)
    age = _decode_age(top["age"], owners) if "age" in top else None
    return StackMessage(
        sender, position, Stack(tuple(slots)), step, skipped, have, tuple(reused), ask, age
    )


def _decode_age(raw: Any, owners: list[str]) -> dict[str, int]:
    """``age``: one integer 0 … ``MAX_AGE_MS`` per slot of the message, in the slots' order."""
    need(isinstance(raw, list), "age", "expected an array")
    need(len(raw) == len(owners), "age", f"{len(raw)} ages for {len(owners)} slots")
    if all(type(a) is int and 0 <= a <= MAX_AGE_MS for a in raw):
        return dict(zip(owners, raw, strict=True))
    pairs = enumerate(zip(owners, raw, strict=True))
    return {owner: as_int(a, f"age[{i}]", 0, MAX_AGE_MS) for i, (owner, a) in pairs}


def _decode_ask(raw: Any, lim: Limits) -> dict[str, str]:
    need(isinstance(raw, list), "ask", "expected an array")
    need(len(raw) <= lim.max_slots, "ask", f"{len(raw)} > {lim.max_slots}", LimitExceeded)
    out: dict[str, str] = {}
    for i, entry in enumerate(raw):
        where = f"ask[{i}]"
        need(isinstance(entry, list) and len(entry) == 2, where, "expected [owner, relay]")
        owner = robot_id(entry[0], where)
        need(owner not in out, where, f"owner {owner!r} twice", InvalidValue)
        out[owner] = robot_id(entry[1], where)
    return out


def _decode_have(raw: Any, lim: Limits) -> dict[str, tuple[int, int]]:
    need(isinstance(raw, list), "have", "expected an array")
    need(len(raw) <= lim.max_slots, "have", f"{len(raw)} > {lim.max_slots}", LimitExceeded)
    out: dict[str, tuple[int, int]] = {}
    for entry in raw:  # the valid case at once (a digest comes with every gossip tick)
        if not (type(entry) is list and len(entry) == 3):
            break
        owner, epoch, stamp = entry
        if not (
            type(epoch) is int
            and type(stamp) is int
            and 0 <= epoch <= MAX_EPOCH
            and 0 <= stamp <= _MAX_STAMP
            and type(owner) is str
            and owner not in out
            and valid_id(owner)
        ):
            break
        out[owner] = (epoch, stamp)
    else:
        return out
    out = {}  # something is wrong: find what, and say where
    for i, entry in enumerate(raw):
        where = f"have[{i}]"
        need(isinstance(entry, list) and len(entry) == 3, where, "expected [owner, epoch, stamp]")
        owner = robot_id(entry[0], where)
        need(owner not in out, where, f"owner {owner!r} twice", InvalidValue)
        out[owner] = (as_int(entry[1], where, 0, MAX_EPOCH), as_int(entry[2], where, 0, _MAX_STAMP))
    return out


@dataclass(frozen=True, slots=True)
class _Header:
    """A slot's header fields, checked; its bodies still as received (``frame.spans``)."""

    frame: SlotFrame
    owner: str
    epoch: int
    stamp: int
    signature: bytes | None


def _slot_header(raw: Any, where: str, signed: bool) -> _Header:
    frame = raw if isinstance(raw, SlotFrame) else None
    fields = frame.fields if frame is not None else raw
    if signed:
        keys_of_slot = _SIGNED_SLOT_KEYS
    else:
        has_epoch = isinstance(fields, dict) and "epoch" in fields
        keys_of_slot = _EPOCH_SLOT_KEYS if has_epoch else _SLOT_KEYS
    s = as_map(fields, where, keys_of_slot)
    owner = robot_id(s["owner"], f"{where}.owner")
    epoch = as_int(s.get("epoch", 0), f"{where}.epoch", 0, MAX_EPOCH)
    signature = None
    if signed:
        signature = s["sig"]
        need(
            isinstance(signature, bytes) and len(signature) == SIGNATURE_BYTES,
            f"{where}.sig",
            f"expected {SIGNATURE_BYTES} bytes",
        )
    stamp = as_int(s["stamp"], f"{where}.stamp", 0, _MAX_STAMP)
    need(frame is not None, where, "expected a slot map")  # every one of a scan is a frame
    assert frame is not None
    return _Header(frame, owner, epoch, stamp, signature)


def _verify(header: _Header, where: str, keys: SigningKeys, buf: bytes) -> None:
    """The owner's signature over the slot's bytes as received (a relay re-sends these bytes),
    against the roster's key: every slot, wanted or not."""
    key = keys.get(header.owner)
    if key is None:
        raise BadSignature(
            f"no signing key for owner {header.owner!r} in the roster", f"{where}.owner"
        )
    (oa, ob), (ra, rb) = header.frame.spans["objects"], header.frame.spans["real"]
    view = memoryview(buf)
    found = digest_of_parts(header.owner, header.epoch, header.stamp, view[oa:ob], view[ra:rb])
    assert header.signature is not None  # a signed message's headers all carry one
    if not verify_digest(key, found, header.signature):
        raise BadSignature(f"the signature of {header.owner} does not verify", f"{where}.sig")


def _decode_slot(
    header: _Header,
    where: str,
    lim: Limits,
    hooks: tuple[Wanted | None, Parsed | None],
    buf: bytes,
    maps: bool,
) -> tuple[str, Slot | None, bool]:
    """The slot's owner, the slot — None when ``wanted`` refuses its version — and whether it is
    one ``parsed`` gave back. ``maps``: the message's version may carry per-object slots (a
    ``real`` map)."""
    wanted, parsed = hooks
    frame, owner, epoch, stamp = header.frame, header.owner, header.epoch, header.stamp
    signature = header.signature
    bodies = {name: memoryview(buf)[a:b] for name, (a, b) in frame.spans.items()}
    if wanted is not None and not wanted(owner, epoch, stamp):
        return owner, None, False
    if parsed is not None:
        before = parsed(owner, epoch, stamp)
        if (
            before is not None
            and before.wire is not None
            and before.wire.fits(before)
            and before.wire.data == memoryview(buf)[frame.start : frame.end]
        ):
            return owner, before, True
    objects = _unpack(bodies["objects"], where)
    need(isinstance(objects, list), f"{where}.objects", "expected an array")
    n = len(objects)
    need(n <= lim.max_objects, f"{where}.objects", f"{n} > {lim.max_objects}", LimitExceeded)
    ids = tuple(objects)
    if not all(type(j) is int and 0 <= j <= _MAX_OBJECT_ID for j in ids):  # which, and why
        ids = tuple(
            as_int(j, f"{where}.objects[{i}]", 0, _MAX_OBJECT_ID) for i, j in enumerate(objects)
        )
    need(len(set(ids)) == n, f"{where}.objects", "duplicate object ids", InvalidValue)
    real = bodies["real"]
    if len(real) and _is_map(real[0]):
        need(
            maps,
            f"{where}.real",
            "expected an array of realisations (a per-object map needs wire version 3 or 4)",
        )
        summary = LocalSummary(ids, (), _decode_objects(real, where, n, lim))
    else:
        summary = LocalSummary(ids, _decode_table(real, where, n, lim))
    wire = WireForm(owner, epoch, stamp, signature, summary, bytes(buf[frame.start : frame.end]))
    return owner, Slot(owner, stamp, summary, epoch, signature, wire), False


def _is_map(first: int) -> bool:
    """Whether a msgpack value that starts with the byte ``first`` is a map."""
    return 0x80 <= first <= 0x8F or first in (0xDE, 0xDF)


def _decode_table(body: memoryview, where: str, n: int, lim: Limits) -> Realisations:
    """A realisation table's ``real`` (docs/wire.md, "Message")."""
    columns = _shared_xi_run(body, n, lim)
    if columns is None:  # the general path: every realisation a map of its own
        columns = _realisation_maps(body, where, n, lim)
    classes, phi, carriers, xi_index = columns
    rows = np.array(list(carriers), dtype=np.int64)
    iu = _tri(n)
    sizes = {"lin": 3 * n, "info": len(iu[0]), "eta": 3 * n}
    arrays = {
        name: _floats([raw[name] for raw in carriers.values()], f"{where}.real", name, count, rows)
        for name, count in sizes.items()
    }
    info = _mirror(arrays["info"], n)
    lin = arrays["lin"].reshape(len(rows), n, 3)
    _raise_remote(numbers_problem(where, phi, lin, info, arrays["eta"], lim, rows))
    xis = [Xi(lin[x], info[x], arrays["eta"][x]) for x in range(len(rows))]
    for a in (classes, phi, xi_index):
        a.flags.writeable = False
    return Realisations(classes, phi, xis, xi_index)


def _decode_objects(body: memoryview, where: str, n: int, lim: Limits) -> ObjectClasses:
    """A per-object slot's ``real`` map (docs/wire.md, "Per-object slots"): its kind and object
    dimension first (a later version may change the rest), then exactly its keys, M, the byte
    counts, and the numbers as a table slot's (log φ per object and class)."""
    field = f"{where}.real"
    raw = _unpack(body, field)
    need(isinstance(raw, dict), field, f"expected a map, got {type(raw).__name__}")
    if "kind" in raw:
        kind = raw["kind"]
        need(isinstance(kind, str), f"{field}.kind", "expected a string")
        need(
            kind == OBJECTS_KIND,
            f"{field}.kind",
            f"{kind!r} is not a known kind (expected {OBJECTS_KIND!r})",
            InvalidValue,
        )
    d = OBJECT_DIM
    if "dim" in raw:
        dim = raw["dim"]
        need(type(dim) is int, f"{field}.dim", "expected an integer")
        need(
            dim in OBJECT_DIMS,
            f"{field}.dim",
            f"objects of dimension {dim} are not supported (known: 3, Pose2; 2, Point2)",
            InvalidValue,
        )
        d = dim
    local_ids = "ids" in raw
    if local_ids:
        value = raw["ids"]
        shown = repr(value[:16]) if isinstance(value, str) else type(value).__name__  # bounded
        need(
            value == LOCAL_IDS_VALUE,
            f"{field}.ids",
            f"{shown} is not a known id kind (expected {LOCAL_IDS_VALUE!r}; a slot of global "
            "ids has no ids)",
            InvalidValue,
        )
        raw = {key: value for key, value in raw.items() if key != "ids"}
    if "xi" in raw:
        form = raw["xi"]
        need(isinstance(form, str), f"{field}.xi", "expected a string")
        need(
            form == SPARSE_XI,
            f"{field}.xi",
            f"{form!r} is not a known ξ form (expected {SPARSE_XI!r}; a dense ξ has no xi)",
            InvalidValue,
        )
        return _decode_sparse(raw, where, n, lim, d, local_ids)
    r = as_map(raw, field, _OBJECTS_KEYS)
    m = as_int(r["m"], f"{field}.m", 1, lim.num_classes)
    counts: dict[str, tuple[np.dtype[Any], int]] = {
        "phi": (_F32, n * m),
        "lin": (_F64, d * n),
        "info": (_F64, len(_tri(n, d)[0])),
        "eta": (_F64, d * n),
    }
    arrays = {name: _blob(r, field, name, dtype, count) for name, (dtype, count) in counts.items()}
    phi = arrays["phi"].reshape(n, m)
    _raise_remote(class_phi_problem(where, phi, lim))
    lin = arrays["lin"].reshape(n, d)
    info = _mirror(arrays["info"][None], n, d)[0]
    eta = arrays["eta"]
    _raise_remote(object_xi_problem(where, lin, info, eta, lim))
    for a in (phi, lin, info, eta):
        a.flags.writeable = False
    return ObjectClasses(phi, Xi(lin, info, eta), local_ids)


def _blob(r: dict[str, Any], field: str, name: str, dtype: np.dtype[Any], count: int) -> Array:
    """The binary ``r[name]`` of ``count`` numbers of ``dtype``, as float64 (length checked)."""
    value = r[name]
    kind_of = "float32" if dtype == _F32 else "float64"
    need(isinstance(value, bytes), f"{field}.{name}", f"expected binary {kind_of} data")
    size = dtype.itemsize * count
    need(len(value) == size, f"{field}.{name}", f"expected {size} bytes, got {len(value)}")
    with np.errstate(invalid="ignore"):  # a signalling NaN: refused as non-finite, later
        return np.frombuffer(value, dtype=dtype).astype(np.float64)


def _decode_sparse(
    raw: dict[str, Any],
    where: str,
    n: int,
    lim: Limits,
    d: int = OBJECT_DIM,
    local_ids: bool = False,
) -> ObjectClasses:
    """A per-object ``real`` map whose ξ is sparse (docs/wire.md, "Sparse ξ"), after its kind,
    dimension and ``xi``: exactly its keys, M, the byte counts (E from ``edges``), log φ, the
    edges, then the numbers of ξ (:func:`sparse_xi_problem`)."""
    field = f"{where}.real"
    r = as_map(raw, field, _SPARSE_KEYS)
    m = as_int(r["m"], f"{field}.m", 1, lim.num_classes)
    phi = _blob(r, field, "phi", _F32, n * m).reshape(n, m)
    lin = _blob(r, field, "lin", _F64, d * n).reshape(n, d)
    upper = d * (d + 1) // 2
    diag = _mirror3(_blob(r, field, "diag", _F32, upper * n).reshape(n, upper))
    raw_edges = r["edges"]
    need(isinstance(raw_edges, bytes), f"{field}.edges", "expected binary uint16 pairs")
    need(
        len(raw_edges) % 4 == 0,
        f"{field}.edges",
        f"expected uint16 pairs (4 bytes each), got {len(raw_edges)} bytes",
    )
    edges = np.frombuffer(raw_edges, dtype=_EDGE_INDEX).astype(np.intp).reshape(-1, 2)
    edge_info = _blob(r, field, "edge_info", _F32, d * d * len(edges)).reshape(-1, d, d)
    eta = _blob(r, field, "eta", _F32, d * n)
    _raise_remote(class_phi_problem(where, phi, lim))
    _raise_remote(sparse_edges_problem(where, edges, n))
    _raise_remote(sparse_xi_problem(where, lin, diag, edges, edge_info, eta, lim))
    for a in (phi, lin, diag, edges, edge_info, eta):
        a.flags.writeable = False
    return ObjectClasses(phi, SparseXi(lin, diag, edges, edge_info, eta), local_ids)


# (R, n) uint8 classes, (R,) log φ, the realisations that carry their ξ (index → their map), and
# (R,) the index of each realisation's ξ among those carriers.
_Columns = tuple[NDArray[np.uint8], Array, dict[int, dict[str, Any]], NDArray[np.intp]]


def _unpack(body: memoryview, where: str) -> Any:
    try:
        return msgpack.unpackb(body, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # as unpacking the whole message would have failed
        raise MalformedMessage(f"not msgpack ({type(exc).__name__}: {exc})", where) from None


def _realisation_maps(body: memoryview, where: str, n: int, lim: Limits) -> _Columns:
    """The realisations of a slot body parsed map by map; raises naming the field at fault."""
    reals = _unpack(body, where)
    need(isinstance(reals, list), f"{where}.real", "expected an array")
    need(len(reals) >= 1, f"{where}.real", "a slot has at least one realisation", InvalidValue)
    need(
        len(reals) <= lim.max_realisations,
        f"{where}.real",
        f"{len(reals)} > {lim.max_realisations}",
        LimitExceeded,
    )
    heads = _well_formed_heads(reals, n, lim)
    if heads is None:  # the field-by-field path names what is wrong
        heads = [_decode_head(r, f"{where}.real[{i}]", n, i, lim) for i, r in enumerate(reals)]
        for i, (_, _, _, ref) in enumerate(heads):
            if ref is not None:
                field = f"{where}.real[{i}].xi"
                carrier = heads[ref][3] is None
                need(carrier, field, "names a realisation without its ξ", InvalidValue)
    carriers = {i: h[2] for i, h in enumerate(heads) if h[3] is None}
    number = {i: x for x, i in enumerate(carriers)}
    classes = np.array([h[0] for h in heads], dtype=np.uint8).reshape(len(heads), n)
    phi = np.array([h[1] for h in heads], dtype=float)
    xi_index = np.array([number[i if h[3] is None else h[3]] for i, h in enumerate(heads)])
    return classes, phi, carriers, xi_index.astype(np.intp)


# A realisation that shares realisation 0's ξ, as ``encode`` writes it for n < 256 objects:
# {"c": bin8 of n bytes, "phi": float64, "xi": 0} — n + 22 bytes whose layout is fixed.
def _ref_record(n: int) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    head = bytes([0x83, 0xA1, ord("c"), 0xC4, n])
    row = head + bytes(n) + b"\xa3phi\xcb" + bytes(8) + b"\xa2xi\x00"
    fixed = np.ones(len(row), dtype=bool)
    fixed[len(head) : len(head) + n] = False  # the classes
    fixed[len(head) + n + 5 : len(head) + n + 13] = False  # log φ
    return np.frombuffer(row, dtype=np.uint8), fixed


@functools.lru_cache(maxsize=64)
def _ref_layout(n: int) -> tuple[NDArray[np.uint8], NDArray[np.intp]]:
    row, fixed = _ref_record(n)
    return row[fixed], np.flatnonzero(fixed)


def _shared_xi_run(body: memoryview, n: int, lim: Limits) -> _Columns | None:
    """The realisations of a slot whose first realisation carries the ξ and every other one
    shares it, read at once: the shared ones are records of one fixed layout (``_ref_record``),
    checked and sliced with numpy instead of unpacked map by map. None when the body is anything
    else — the general path then parses it (and names the field at fault, if any)."""
    if n >= 256 or len(body) < 2:
        return None
    first = body[0]
    if 0x91 <= first <= 0x9F:
        count, at = first & 0x0F, 1
    elif first == 0xDC and len(body) >= 3:
        count, at = int.from_bytes(body[1:3], "big"), 3
    else:
        return None
    if count > lim.max_realisations:
        return None
    size = n + 22
    rest = len(body) - (count - 1) * size  # where the shared realisations would begin
    if count < 2 or rest <= at:
        return None
    try:
        carrier = msgpack.unpackb(body[at:rest], raw=False, strict_map_key=True, use_list=True)
    except Exception:
        return None
    if not (type(carrier) is dict and len(carrier) == 5 and carrier.keys() == _REAL_KEYS):
        return None
    c, phi0 = carrier["c"], carrier["phi"]
    if not (type(c) is bytes and len(c) == n and type(phi0) is float):
        return None
    records = np.frombuffer(body[rest:], dtype=np.uint8).reshape(count - 1, size)
    want, where = _ref_layout(n)
    if not (records[:, where] == want).all():
        return None
    classes = np.empty((count, n), dtype=np.uint8)
    classes[0] = np.frombuffer(c, dtype=np.uint8)
    classes[1:] = records[:, 5 : 5 + n]
    if n and int(classes.max()) >= lim.num_classes:
        return None
    phi = np.empty(count)
    phi[0] = phi0
    phi[1:] = np.ascontiguousarray(records[:, 10 + n : 18 + n]).view(">f8")[:, 0]
    return classes, phi, {0: carrier}, np.zeros(count, dtype=np.intp)


_Head = tuple[tuple[int, ...], float, dict[str, Any], int | None]


def _well_formed_heads(reals: list[Any], n: int, lim: Limits) -> list[_Head] | None:
    """What :func:`_decode_head` gives for every realisation, checked all at once (a slot's
    realisations are hundreds of small maps: one pass over them and numpy for the classes and
    the ξ references, instead of a call per field), or None if any realisation breaks a rule —
    :func:`_decode_head` then finds which and says why. Same rules: a map with exactly the keys
    of a realisation that carries its ξ or of one that names an earlier carrier, n class bytes
    below ``num_classes``, a number log φ (not a bool), a ξ reference to an earlier carrier."""
    cs: list[Any] = []
    phis: list[Any] = []
    refs: list[Any] = []
    own: list[bool] = []
    for r in reals:
        if type(r) is not dict:
            return None
        if len(r) == 3 and r.keys() == _REF_KEYS:
            refs.append(r["xi"])
            own.append(False)
        elif len(r) == 5 and r.keys() == _REAL_KEYS:
            refs.append(0)
            own.append(True)
        else:
            return None
        cs.append(r["c"])
        phis.append(r["phi"])
    if not all(type(c) is bytes and len(c) == n for c in cs):
        return None
    if not all(type(v) is float or type(v) is int for v in phis):
        return None
    if not all(type(x) is int for x in refs):
        return None
    try:
        phi = [float(v) for v in phis]
        ref = np.array(refs, dtype=np.int64)
    except (OverflowError, ValueError):
        return None
    classes = np.frombuffer(b"".join(cs), dtype=np.uint8).reshape(len(cs), n)
    if n and int(classes.max()) >= lim.num_classes:
        return None
    carries = np.array(own, dtype=bool)
    shares = ~carries
    index = np.arange(len(ref))
    if np.any(shares & ((ref < 0) | (ref >= index))):
        return None
    if np.any(shares & ~carries[np.clip(ref, 0, max(0, len(ref) - 1))]):
        return None
    return [
        (tuple(c), phi[i], reals[i], None if own[i] else int(ref[i]))
        for i, c in enumerate(classes.tolist())
    ]


def _decode_head(raw: Any, where: str, n: int, i: int, lim: Limits) -> _Head:
    """Classes, log φ and the raw float blobs of realisation ``i``, and the index of the earlier
    realisation whose ξ it shares (None when it carries its own)."""
    shares = isinstance(raw, dict) and "xi" in raw
    r = as_map(raw, where, _REF_KEYS if shares else _REAL_KEYS)
    ref = None
    if shares:
        ref = as_int(r["xi"], f"{where}.xi", 0, max(0, i - 1))
        need(ref < i, f"{where}.xi", "must name an earlier realisation", InvalidValue)
    c = r["c"]
    need(isinstance(c, bytes) and len(c) == n, f"{where}.c", f"expected {n} class bytes")
    classes = tuple(c)
    need(
        all(v < lim.num_classes for v in classes),
        f"{where}.c",
        f"class ≥ {lim.num_classes}",
        InvalidValue,
    )
    phi = r["phi"]
    need(
        isinstance(phi, float | int) and not isinstance(phi, bool),
        f"{where}.phi",
        "expected a number",
    )
    return classes, float(phi), r, ref


def _raise_remote(problem: Problem | None) -> None:
    if problem is not None:
        error, field, message = problem
        raise error(message, field)
