"""Issue 47's latency figure: the age of information (AoI) on an 8-robot chain at a 0.5 s step.

Eight agent processes 8 m apart on a line (``sim.line_world.line_world``: range 10 m, so only
neighbours hear each other), whose Zenoh links join neighbours only (gossip scouting off),
realtime at a 0.5 s step: for every robot i, peer j and step k of j, the time from the end of j's
step k to the moment i's fusion first includes j's version k (``deploy.launch.aoi``, one host's
monotonic clock; docs/results.md, "Age of information"). Reported overall and per hop count |i − j|
as p50 / p99 / max, against the target p99 ≤ 0.5 s + 30 ms per hop: a version must wait for the
receiver's next step (up to one period) to be fused, and each relay may add 30 ms.

The relay is a parameter: :data:`RELAYS` names each way of relaying measured, with the launch
plan's fields that select it; every one runs in the same invocation, one launch after the other,
so that their rows stand side by side: the event-driven relay (``relay = "event"``, the default
since issue 47: a slot a neighbour asked for goes as soon as it was merged) and the relay on the
gossip timer (``"tick"``, before), both with delta gossip and asks (``stack_gossip = "ask"``).

Beside them, for each relay, what the agents themselves say (issue 47, item 1: holding times,
which need no shared clock): per estimate, the largest age of its fused peers' versions as the
robot summed it, minus the age this host's clock gives the same version.
"""

from __future__ import annotations

import asyncio
import dataclasses
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.core import GOSSIP_PERIOD_S
from bench import Result
from deploy.launch import Launcher, LaunchPlan
from deploy.launch.aoi import AgeOfInformation, holding_gaps
from sim.line_world import line_world
from sim.loader import parse_scenario

ROBOTS = 8
PERIOD_S = 0.5
STEPS = 40
TARGET_BASE_MS = 1e3 * PERIOD_S  # the receiver's next step
TARGET_PER_HOP_MS = 30.0
# Label → the LaunchPlan fields that select the relay (the other fields are the same for all).
RELAYS: dict[str, dict[str, Any]] = {
    "event": {"stack_gossip": "ask", "relay": "event"},
    "timer": {"stack_gossip": "ask", "relay": "tick"},
}

_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


def target_ms(hops: int) -> float:
    """The issue's p99 target at ``hops`` hops."""
    return TARGET_BASE_MS + TARGET_PER_HOP_MS * hops


def chain_aoi(
    tmp: Path, relay: Mapping[str, Any], robots: int = ROBOTS, steps: int = STEPS
) -> tuple[AgeOfInformation, NDArray[np.float64]]:
    """The AoI of a realtime launch of ``robots`` agents on a neighbour-only chain, with the
    plan fields ``relay``, and the gaps (ms) between the ages the agents said by holding times
    and this host's clock's (``deploy.launch.aoi.holding_gaps``)."""
    ids = [f"r{i}" for i in range(1, robots + 1)]
    text = line_world(robots, steps=steps)
    path = tmp / "chain.toml"
    path.write_text(text, encoding="utf-8")
    neighbours = {r: [ids[j] for j in (i - 1, i + 1) if 0 <= j < robots] for i, r in enumerate(ids)}
    name = "-".join(f"{v}" for v in relay.values()) or "default"
    plan = LaunchPlan(
        parse_scenario(text, str(path)), 0, ids, tmp / f"aoi-{name}", mode="realtime",
        period=PERIOD_S, gossip_period=GOSSIP_PERIOD_S, fleet="aoi", zenoh_neighbours=neighbours,
        publish_local=False, **relay,
    )  # fmt: skip
    outcome = asyncio.run(Launcher(plan).run())
    assert outcome.aoi is not None
    c = outcome.collected
    return outcome.aoi, holding_gaps(c.ended, c.fused_log, c.age_log)


def holding_rows(label: str, gaps: NDArray[np.float64]) -> list[Result]:
    """The agents' own ages (holding times, no shared clock) against this host's clock."""
    if not gaps.size:
        _notes.append(f"holding times ({label} relay): no estimate gave the age of every peer")
        return []
    p50, p99 = np.percentile(gaps, [50, 99])
    return [
        Result(
            f"holding-time age − one-clock age, per estimate, {label} relay (ms)",
            int(gaps.size),
            float(p50),
            note=f"p50 {p50:+.1f} ms, p99 {p99:+.1f}, min {gaps.min():+.1f}, max "
            f"{gaps.max():+.1f}: the oldest fused peer version of each estimate, as the robot "
            "said it (summed holding times, transits left out) and as this host timed it",
        )
    ]


def aoi_rows(label: str, aoi: AgeOfInformation, scope: str = "") -> list[Result]:
    """One row for every sample, then one per hop count, each its p99 in ms against the target."""
    doc = aoi.document()
    if not doc["samples"]:
        _notes.append(f"AoI ({label} relay): no version timed")
        return []
    per_hop = {h: f for h, f in doc["by_hops"].items() if h != "unlinked"}
    verdicts = {h: f["p99_ms"] <= target_ms(int(h)) for h, f in per_hop.items()}
    met = "met" if all(verdicts.values()) and "unlinked" not in doc["by_hops"] else "NOT met"
    rows = [
        Result(
            f"AoI p99, {ROBOTS}-robot chain at {PERIOD_S:g} s steps, {label} relay{scope}",
            doc["samples"],
            doc["p99_ms"],
            note=f"p50 {doc['p50_ms']:.0f} ms, max {doc['max_ms']:.0f} ms over "
            f"{doc['samples']} (robot, peer, step), {doc['unreached']} never fused by the end; "
            f"target p99 ≤ {TARGET_BASE_MS:.0f} ms + {TARGET_PER_HOP_MS:.0f} ms per hop at "
            f"every hop count: {met}",
        )
    ]
    for h, f in per_hop.items():
        verdict = "met" if verdicts[h] else "NOT met"
        rows.append(
            Result(
                f"AoI p99 at {h} hop{'s' if h != '1' else ''}, {label} relay{scope}",
                f["samples"],
                f["p99_ms"],
                note=f"p50 {f['p50_ms']:.0f} ms, max {f['max_ms']:.0f} ms; target "
                f"≤ {target_ms(int(h)):.0f} ms: {verdict}",
            )
        )
    return rows


# Steps in which the robots meet: a robot asks a neighbour for an owner it does not hear only
# once that neighbour's digest showed the owner, so the first versions cross the chain by
# digests (a gossip period a hop), whatever the relay. The rows after them show the relay alone.
MEET_STEPS = 2


def after_meeting(aoi: AgeOfInformation, steps: int = MEET_STEPS) -> AgeOfInformation:
    """The samples of ``aoi`` of the owners' steps after the first ``steps``."""
    keep = aoi.step > steps
    return dataclasses.replace(
        aoi,
        age_s=aoi.age_s[keep],
        hops=aoi.hops[keep],
        owner=tuple(o for o, k in zip(aoi.owner, keep, strict=True) if k),
        receiver=tuple(r for r, k in zip(aoi.receiver, keep, strict=True) if k),
        step=aoi.step[keep],
    )


def run(relays: Mapping[str, Mapping[str, Any]] | None = None) -> list[Result]:
    """Every relay of ``relays`` (default :data:`RELAYS`) on the same chain, in turn."""
    _notes.clear()
    rows: list[Result] = []
    with tempfile.TemporaryDirectory() as d:
        for label, fields in (relays or RELAYS).items():
            aoi, gaps = chain_aoi(Path(d), fields)
            rows += aoi_rows(label, aoi)
            rows += holding_rows(label, gaps)
            rows += aoi_rows(label, after_meeting(aoi), f", steps after the first {MEET_STEPS}")
    return rows
