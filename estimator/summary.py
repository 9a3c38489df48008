"""The numeric content of a slot: a local belief summarised per class realisation (ξ, φ), or per
object (one ξ and a class log φ per object, :class:`ObjectClasses`)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np
from numpy.typing import NDArray

from estimator.sparse_xi import SparseXi
from estimator.xi import Xi

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class Realisation:
    """One class realisation of the owner's objects and its summary.

    ``classes`` (n,) class indices aligned with the slot's object ids; ``log_phi`` = log w − log
    P(C); ``xi`` the owner's objects' Gaussian under this realisation.
    """

    classes: tuple[int, ...]
    log_phi: float
    xi: Xi

    @property
    def lin(self) -> Array:
        return self.xi.lin

    @property
    def info(self) -> Array:
        return self.xi.info

    @property
    def eta(self) -> Array:
        return self.xi.eta


class Realisations(Sequence[Realisation]):
    """R realisations held as columns: ``classes`` (R, n) class indices, ``log_phi`` (R,), and
    the index ``xi_index`` (R,) of each one's ξ in ``xis``. What a decoder makes: a slot of the
    default belief is one ξ and hundreds of (classes, log φ) rows, which numpy reads and checks
    at once, without an object per row. Indexing and iterating give :class:`Realisation` s that
    share the very ``Xi`` objects of ``xis``. The arrays must not be changed (the decoder gives
    read-only ones)."""

    __slots__ = ("_distinct", "classes", "log_phi", "xi_index", "xis")

    def __init__(
        self,
        classes: NDArray[np.integer],
        log_phi: Array,
        xis: Sequence[Xi],
        xi_index: NDArray[np.integer],
    ) -> None:
        if classes.ndim != 2 or log_phi.shape != (len(classes),) or xi_index.shape != log_phi.shape:
            raise ValueError("realisation columns: classes (R, n), log_phi (R,), xi_index (R,)")
        self.classes = classes
        self.log_phi = log_phi
        self.xis = tuple(xis)
        self.xi_index = xi_index
        self._distinct: tuple[list[Xi], list[int]] | None = None

    def distinct_xi(self) -> tuple[list[Xi], list[int]]:
        """As :meth:`LocalSummary.distinct_xi` (made once: the columns never change)."""
        if self._distinct is None:
            self._distinct = _first_use(self.xis, self.xi_index)
        xis, which = self._distinct
        return list(xis), list(which)

    def __len__(self) -> int:
        return len(self.log_phi)

    @overload
    def __getitem__(self, i: int) -> Realisation: ...

    @overload
    def __getitem__(self, i: slice) -> tuple[Realisation, ...]: ...

    def __getitem__(self, i: int | slice) -> Realisation | tuple[Realisation, ...]:
        if isinstance(i, slice):
            return tuple(self[j] for j in range(*i.indices(len(self))))
        i = range(len(self))[i]  # bounds and negative indices as a tuple has them
        classes = tuple(int(c) for c in self.classes[i])
        return Realisation(classes, float(self.log_phi[i]), self.xis[int(self.xi_index[i])])

    def __iter__(self) -> Iterator[Realisation]:
        return (self[i] for i in range(len(self)))


@dataclass(frozen=True, slots=True, eq=False)
class ObjectClasses:
    """The class summary of a belief with per-object class beliefs (``BeliefConfig.classes =
    "per_object"``; docs/estimator.md, "Per-object classes"): ``log_phi`` (n, M), every object's
    class log-evidence with the class prior divided out (P(c_j) ∝ P(c) · exp(log_phi[j]) on the
    owner's data alone; defined up to a constant per row), and the one ξ of its continuous
    belief: dense (:class:`Xi`, the owner's exact Λ) or, with ``BeliefConfig.xi = "sparse"``,
    its conservative sparse form (``estimator.sparse_xi.SparseXi``: Λ_s ⪯ Λ on a Bayes net's
    moral graph, float32 values). ``local_ids``: the objects' ids are the owner's robot-local
    ones (frames without global ids, issue 45): a receiver maps them onto its own objects
    (``estimator.fleet_association``) and never reads them as global ids. Kept read-only."""

    log_phi: Array
    xi: Xi | SparseXi
    local_ids: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class LocalSummary:
    """A local belief over the owner's objects ``object_ids``, summarised in one of two kinds:

    - a realisation table (the joint class realisations of ``--hypotheses paper``/``exact`` and
      of ``classes = "joint"``): every unpruned realisation, a tuple of :class:`Realisation` or
      the same as columns (:class:`Realisations`); ``per_object`` None;
    - per object (``per_object`` set): one ξ and an (n, M) class log φ; ``realisations`` empty.
    """

    object_ids: tuple[int, ...]
    realisations: tuple[Realisation, ...] | Realisations
    per_object: ObjectClasses | None = None

    @property
    def kind(self) -> str:
        """``"per_object"`` or ``"table"``."""
        return "table" if self.per_object is None else "per_object"

    def distinct_xi(self) -> tuple[list[Xi], list[int]]:
        """The distinct ξ of the realisations (by identity, in order of first use) and the index
        of each realisation's ξ in that list (per object: the one ξ, and no realisation; a
        sparse ξ in its dense form, made anew at each call)."""
        if self.per_object is not None:
            xi = self.per_object.xi
            return [xi if isinstance(xi, Xi) else xi.dense()], []
        rs = self.realisations
        if isinstance(rs, Realisations):
            return rs.distinct_xi()
        index: dict[int, int] = {}
        xis: list[Xi] = []
        which = []
        for r in rs:
            i = index.get(id(r.xi))
            if i is None:
                i = index[id(r.xi)] = len(xis)
                xis.append(r.xi)
            which.append(i)
        return xis, which

    def class_matrix(self) -> NDArray[np.int64]:
        """(R, n) class indices of the realisations."""
        rs = self.realisations
        if isinstance(rs, Realisations):
            return rs.classes.astype(np.int64)
        return np.array([r.classes for r in rs], dtype=np.int64).reshape(len(rs), -1)

    def log_phis(self) -> Array:
        """(R,) log φ of the realisations."""
        rs = self.realisations
        if isinstance(rs, Realisations):
            return rs.log_phi
        return np.array([r.log_phi for r in rs], dtype=float)

    def robot_local(self) -> LocalSummary:
        """This per-object summary, stating that its object ids are its owner's robot-local
        ones (``ObjectClasses.local_ids``)."""
        if self.per_object is None:
            raise ValueError("only a per-object summary has robot-local ids")
        po = self.per_object
        return LocalSummary(self.object_ids, (), ObjectClasses(po.log_phi, po.xi, True))


def _first_use(xis: Sequence[Xi], index: NDArray[np.integer]) -> tuple[list[Xi], list[int]]:
    """``xis`` renumbered in order of first use by ``index``, the unused left out (and a ξ held
    twice by identity, once)."""
    if len(xis) == 1:  # every index is 0: the default belief's one ξ
        return [xis[0]], [0] * len(index)
    used, first, inverse = np.unique(index, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # the used ξ by first use
    out: list[Xi] = []
    by_id: dict[int, int] = {}
    rank = np.empty(len(used), dtype=np.intp)
    for u in order:
        x = xis[int(used[u])]
        rank[u] = by_id.setdefault(id(x), len(out))
        if rank[u] == len(out):
            out.append(x)
    return out, rank[inverse].tolist()


@dataclass(frozen=True, slots=True, eq=False)
class Slot:
    """Robot ``owner``'s local summary at its own step ``stamp`` (stamps are per-owner counters:
    no clock synchronisation is assumed). The one slot type from the wire to the fusion."""

    owner: str
    stamp: int
    summary: LocalSummary
    # The owner's epoch (docs/wire.md, "Versions and epochs"): a robot that lost its journal
    # starts its stamps again under a higher epoch, so a version is (epoch, stamp). Wire version
    # 2 adds the owner's Ed25519 signature over the slot's canonical bytes (None: unsigned). The
    # estimator never reads the signature: a relay re-sends it with the slot.
    epoch: int = 0
    signature: bytes | None = None
    # The slot's bytes as the codec validated or made them (a relay re-sends them untouched);
    # the estimator never reads them.
    wire: WireForm | None = None

    @property
    def version(self) -> tuple[int, int]:
        """(epoch, stamp): a newer version is a greater one."""
        return (self.epoch, self.stamp)


@dataclass(frozen=True, slots=True, eq=False)
class WireForm:
    """A slot's msgpack bytes (``data``) and the fields they were made from: valid for a slot
    only while its owner, version, signature and summary object are still these (a slot changed
    with ``dataclasses.replace`` is encoded anew)."""

    owner: str
    epoch: int
    stamp: int
    signature: bytes | None
    summary: LocalSummary
    data: bytes

    def fits(self, slot: Slot) -> bool:
        return (
            slot.summary is self.summary
            and slot.owner == self.owner
            and slot.epoch == self.epoch
            and slot.stamp == self.stamp
            and slot.signature == self.signature
        )
