"""Age of information (issue 47): how long a robot's step takes to reach another robot's fusion.

For every pair (i, j) and every step k of robot j, the age of information of j's step k at i is
the time from the end of j's step k to the moment i's fusion first includes a version ≥ k of j's
slot: a later version counts too, since it carries step k's information (a robot that fuses
j's version k + 2 directly never needed k + 1). Both ends are read on one host's monotonic clock:
the end of j's step k is when j's estimate of k arrived, and i's fusion includes the version
from the arrival of the first estimate of i whose ``fused`` map (docs/wire.md, "Estimates")
says so; the two estimates' transit times then mostly cancel.

The hop count of a pair is the length of the shortest path from j to i in the link graph the
caller gives (a launch's Zenoh topology, or the simulated links in force at step k). Versions
that never reached a robot by the end of the run are counted as ``unreached``, not timed.
Nothing here reads a clock: the times come in with the data (docs/results.md).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

# The percentiles reported next to the maximum (as step times: deploy.study.archive).
PERCENTILES = (50, 99)
UNLINKED = -1  # the hop count of a pair with no path in the link graph at that step

# (arrival time, robot, step, {owner: stamp} its fusion had integrated by the end of the step)
FusedRecord = tuple[float, str, int, Mapping[str, int]]
HopCount = Callable[[str, str, int], int]  # (owner j, receiver i, step k) → hops, or UNLINKED


@dataclass(frozen=True, slots=True)
class AgeOfInformation:
    """The ages of one run: ``age_s`` (n,) seconds, ``hops`` (n,) the pair's hop count at the
    step (UNLINKED: no path), ``owner``, ``receiver`` (n,) robot ids and ``step`` (n,) the
    owner's step k, one entry per (i, j, k) timed; ``unreached``: the (i, j, k) whose version
    never reached i's fusion by the end of the run."""

    age_s: NDArray[np.float64]
    hops: NDArray[np.int64]
    owner: tuple[str, ...]
    receiver: tuple[str, ...]
    step: NDArray[np.int64]
    unreached: int

    def document(self) -> dict[str, Any]:
        """The results.json entry (docs/results.md, "Age of information"): the figures of every
        sample and of each hop count."""
        by_hops = {
            ("unlinked" if h == UNLINKED else str(h)): _figures(self.age_s[self.hops == h])
            for h in sorted(set(self.hops.tolist()), key=lambda h: (h == UNLINKED, h))
        }
        return {**_figures(self.age_s), "unreached": self.unreached, "by_hops": by_hops}

    def arrays(self, robots: Sequence[str]) -> dict[str, NDArray[Any]]:
        """The samples as results.npz arrays (docs/results.md): ``aoi/age_ms`` float64,
        ``aoi/hops``, ``aoi/owner`` and ``aoi/receiver`` (indices into ``robots``) and
        ``aoi/step``, int64, all (n,)."""
        index = {r: i for i, r in enumerate(robots)}
        return {
            "aoi/age_ms": 1e3 * self.age_s,
            "aoi/hops": self.hops,
            "aoi/owner": np.array([index[r] for r in self.owner], dtype=np.int64),
            "aoi/receiver": np.array([index[r] for r in self.receiver], dtype=np.int64),
            "aoi/step": self.step,
        }

    def line(self) -> str:
        """One line for a summary: the overall figures and the p99 per hop count."""
        if not self.age_s.size:
            return f"age of information: no version timed ({self.unreached} never fused)"
        doc = self.document()
        per_hop = ", ".join(f"{h}: {f['p99_ms']:.0f}" for h, f in doc["by_hops"].items())
        return (
            f"age of information over {doc['samples']} (robot, peer, step): p50 "
            f"{doc['p50_ms']:.0f} ms, p99 {doc['p99_ms']:.0f} ms, max {doc['max_ms']:.0f} ms; "
            f"p99 ms by hops {per_hop}; {self.unreached} versions never fused"
        )


def _figures(age_s: NDArray[np.float64]) -> dict[str, Any]:
    if not age_s.size:
        return {"samples": 0, **{f"p{p}_ms": None for p in PERCENTILES}, "max_ms": None}
    ms = 1e3 * age_s
    tails = {f"p{p}_ms": round(float(np.percentile(ms, p)), 3) for p in PERCENTILES}
    return {"samples": int(ms.size), **tails, "max_ms": round(float(ms.max()), 3)}


def age_of_information(
    robots: Sequence[str],
    ended: Mapping[tuple[str, int], float],
    fused: Iterable[FusedRecord],
    hops: HopCount,
) -> AgeOfInformation:
    """The age of every version of ``ended`` (robot j, step k) → when j's step k ended, at every
    other robot of ``robots``, from ``fused``: each robot's integrated versions as they were
    reported, with the time of the report (any order; a robot's reports are taken in time
    order, and a version counts as fused from the first report that holds it or a later one)."""
    latest: dict[tuple[str, str], int] = {}  # (receiver, owner) → newest stamp reported so far
    first: dict[tuple[str, str, int], float] = {}  # (receiver, owner, k) → first time fused
    by_owner: dict[str, list[int]] = {}
    for owner, k in ended:
        by_owner.setdefault(owner, []).append(k)
    for steps in by_owner.values():
        steps.sort()
    for t, receiver, _, stamps in sorted(fused, key=lambda r: (r[0], r[1], r[2])):
        for owner, stamp in stamps.items():
            before = latest.get((receiver, owner), -1)
            if stamp <= before or owner == receiver:
                continue
            latest[(receiver, owner)] = stamp
            steps = by_owner.get(owner, [])
            lo, hi = np.searchsorted(steps, [before, stamp], side="right")
            for k in steps[lo:hi]:  # before < k ≤ stamp: first included now
                first[(receiver, owner, k)] = t
    rows = [
        (t - ended[(owner, k)], hops(owner, receiver, k), owner, receiver, k)
        for (receiver, owner, k), t in first.items()
        if receiver in robots
    ]
    expected = sum(1 for owner, _ in ended for r in robots if r != owner)
    return AgeOfInformation(
        np.array([r[0] for r in rows], dtype=np.float64),
        np.array([r[1] for r in rows], dtype=np.int64),
        tuple(r[2] for r in rows),
        tuple(r[3] for r in rows),
        np.array([r[4] for r in rows], dtype=np.int64),
        expected - len(rows),
    )


def holding_gaps(
    ended: Mapping[tuple[str, int], float],
    fused: Iterable[FusedRecord],
    said: Iterable[tuple[float, str, int, int]],
) -> NDArray[np.float64]:
    """Per estimate whose robot said how old its peers' information was by holding times
    (``said``: arrival, robot, step, the largest age in ms; ``agents.ages``), that age minus the
    one this host's clock measures for the same estimate: the arrival of the estimate minus the
    end of the owner's step of the oldest fused version (``ended``). In ms; estimates for which a
    fused version's step has no known end are left out. Near 0 when the holding times account for
    the whole age; below by the transits they leave out."""
    versions = {(r[1], r[2]): r[3] for r in fused}
    gaps = []
    for at, robot, k, ms in said:
        stamps = versions.get((robot, k), {})
        ends = [ended.get((o, s)) for o, s in stamps.items() if o != robot]
        if ends and all(e is not None for e in ends):
            gaps.append(ms - 1e3 * (at - min(e for e in ends if e is not None)))
    return np.array(gaps, dtype=np.float64)


def hop_counts(edges: Mapping[str, Iterable[str]], source: str) -> dict[str, int]:
    """The fewest hops from ``source`` to every robot it reaches over ``edges`` (robot → the
    robots it sends to), by breadth-first search."""
    out = {source: 0}
    queue = deque([source])
    while queue:
        at = queue.popleft()
        for nxt in edges.get(at, ()):
            if nxt not in out:
                out[nxt] = out[at] + 1
                queue.append(nxt)
    return out


def undirected(neighbours: Mapping[str, Iterable[str]]) -> dict[str, set[str]]:
    """``neighbours`` (robot → its Zenoh neighbours) with every link both ways."""
    out: dict[str, set[str]] = {}
    for a, peers in neighbours.items():
        for b in peers:
            out.setdefault(a, set()).add(b)
            out.setdefault(b, set()).add(a)
    return out


def senders_to_receivers(heard: Mapping[str, Iterable[str]]) -> dict[str, set[str]]:
    """A link verdict (receiver → the senders it hears) as sender → the receivers that hear it,
    the direction information flows in."""
    out: dict[str, set[str]] = {}
    for receiver, senders in heard.items():
        for s in senders:
            out.setdefault(s, set()).add(receiver)
    return out


def link_hops(
    links_of_step: Callable[[int], Mapping[str, Iterable[str]]],
    robots: Sequence[str],
    neighbours: Mapping[str, Iterable[str]] | None = None,
) -> HopCount:
    """The hop count of (owner, receiver, k) over the links in force at step k
    (``links_of_step(k)``: receiver → the senders it hears), only those a Zenoh topology
    ``neighbours`` (robot → its neighbours; None: a full mesh) also joins. Each step's counts
    are made once, when first asked for."""
    zenoh = None if neighbours is None else undirected(neighbours)
    tables: dict[int, dict[str, dict[str, int]]] = {}

    def hops(owner: str, receiver: str, k: int) -> int:
        if k not in tables:
            graph = senders_to_receivers(links_of_step(k))
            if zenoh is not None:
                graph = {s: {r for r in rs if r in zenoh.get(s, ())} for s, rs in graph.items()}
            tables[k] = {r: hop_counts(graph, r) for r in robots}
        return tables[k].get(owner, {}).get(receiver, UNLINKED)

    return hops
