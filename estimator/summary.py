"""The numeric content of a slot: a local belief summarised per class realisation (ξ, φ)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class Xi:
    """ξ of Eq. 18: a prior-divided joint Gaussian over the owner's n objects in information form.

    ``lin`` (n, 3) linearisation poses; ``info`` (3n, 3n) Λ, symmetric positive definite; ``eta``
    (3n,) η, so that ξ ∝ exp(−½ δᵀΛδ + ηᵀδ) over tangent perturbations δ at ``lin``. Several
    realisations of one slot may share one ξ (the same object): every realisation of a belief
    whose hypotheses share one continuous belief does (docs/estimator.md).
    """

    lin: Array
    info: Array
    eta: Array


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


@dataclass(frozen=True, slots=True, eq=False)
class LocalSummary:
    """Every unpruned realisation of a local belief over the owner's objects ``object_ids``."""

    object_ids: tuple[int, ...]
    realisations: tuple[Realisation, ...]

    def distinct_xi(self) -> tuple[list[Xi], list[int]]:
        """The distinct ξ of the realisations (by identity, in order of first use) and the index
        of each realisation's ξ in that list."""
        index: dict[int, int] = {}
        xis: list[Xi] = []
        which = []
        for r in self.realisations:
            i = index.get(id(r.xi))
            if i is None:
                i = index[id(r.xi)] = len(xis)
                xis.append(r.xi)
            which.append(i)
        return xis, which


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
