"""Issue 5's figures: gossip latency against raw Zenoh, relay latency per hop, and how many agents
one 2-core machine runs in realtime mode, with CPU and memory per agent.

- Gossip latency (bench/gossip_paths.py): a real paper stack put on one Zenoh session → decoded
  and merged behind a second session, on the event loop and through a running agent, against the
  raw Zenoh put → subscriber-callback latency for the same payload, measured in the same run.
  Targets: ≤ 2 × raw + decode time (issue 5); ≤ 1.5 × raw (issue 14, for a relayed slot: every
  slot of the stack is a version the receiver lacks, so each is decoded and validated once, as a
  relay's peer must). A fifth row times the floor of any validating receiver: the decode on
  Zenoh's own thread, before any hand-off.
- Relay per hop: 4 agent processes on a line whose Zenoh links only join neighbours (gossip
  scouting off), realtime; the time from a new version of r1's slot in r1's stack to the same
  version in r4's stack, over 3 hops; with delta gossip against full gossip, in the same run. With
  full gossip a hop costs on average half a gossip period plus the transit; delta gossip first
  gives a peer a period to get the version from its owner (docs/wire.md, "Delta gossip"), unless
  the peer asked for it (the default, ``stack_gossip = "ask"``): a robot asks a neighbour to push
  the slots of the robots it does not hear, and the neighbour sends each new version with its
  next tick (docs/wire.md, "Asks").
- Capacity: bench/bench_capacity.py.
"""

from __future__ import annotations

import asyncio
import os
import statistics
import tempfile
import time
from pathlib import Path

from bench import Result
from bench.gossip_paths import gossip_rows
from deploy.launch import Launcher, LaunchOutcome, LaunchPlan
from sim.generate import line_world
from sim.loader import parse_scenario

PERIOD_S = 0.5  # the realtime step period (the scenario format has no rate; see docs/agents.md)
GOSSIP_S = 0.25

_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


def _run_launch(
    plan: LaunchPlan, sample: bool = False
) -> tuple[LaunchOutcome, dict[str, dict[str, float]]]:
    launcher = Launcher(plan)
    usage: dict[str, dict[str, float]] = {}

    def on_step(conductor: object, k: int) -> None:
        if not sample:
            return
        for r, a in launcher.agents.items():
            if a.proc is None or a.proc.poll() is not None:
                continue
            cpu, rss = _proc_usage(a.proc.pid)
            u = usage.setdefault(r, {"cpu0": cpu, "t0": time.monotonic(), "rss": 0.0})
            u["cpu"], u["t"], u["rss"] = cpu, time.monotonic(), max(u["rss"], rss)

    outcome = asyncio.run(launcher.run(on_step))
    return outcome, usage


def _proc_usage(pid: int) -> tuple[float, float]:
    """CPU seconds (user + system) and resident memory in MB of ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu = (int(fields[11]) + int(fields[12])) / ticks
    rss_pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    return cpu, rss_pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def _relay_rows(tmp: Path) -> list[Result]:
    """Relay per hop with the default (delta gossip with asks) and with ``"delta"`` (no asks),
    against full gossip, the same line run with each in turn."""
    full = _relay_per_hop(tmp, "full")
    delta = _relay_per_hop(tmp, "delta")
    ask = _relay_per_hop(tmp, "ask")
    if not full or not delta or not ask:
        _notes.append("relay: r4 never held a version of r1's slot (no figure)")
        return []
    return [
        Result(
            "relay latency per hop (4 agents on a line)",
            len(ask),
            statistics.median(ask),
            baseline_ms=statistics.median(full),
            note=f"median over {len(ask)} versions of r1's slot reaching r4 over 3 hops, the "
            f"default (each robot asks a neighbour to push it the slots of the robots it does not "
            f"hear, and the neighbour sends each new version with its next tick); gossip period "
            f"{GOSSIP_S * 1e3:.0f} ms; baseline = full gossip, the same launch ({len(full)} "
            f"versions): every tick re-sends every slot, so a hop waits for the next tick "
            f'(≈ {GOSSIP_S * 500:.0f} ms + transit) (docs/wire.md, "Asks")',
        ),
        Result(
            'relay latency per hop, stack_gossip = "delta" (4 agents on a line)',
            len(delta),
            statistics.median(delta),
            baseline_ms=statistics.median(full),
            note=f"median over {len(delta)} versions, as above, without asks: a version goes to a "
            f"peer whose digest lacks it once that peer could have had it from its owner, a "
            f'gossip period after it came (docs/wire.md, "Delta gossip")',
        ),
    ]


def _relay_per_hop(tmp: Path, gossip: str) -> list[float]:
    """The time per hop (ms) of every version of r1's slot that reached r4 over a 4-robot line
    whose Zenoh links join neighbours only, with ``gossip`` (``stack_gossip``)."""
    robots = [f"r{i}" for i in range(1, 5)]
    text = line_world(len(robots), steps=24)
    path = tmp / "line.toml"
    path.write_text(text, encoding="utf-8")
    s = parse_scenario(text, str(path))
    neighbours = {
        r: [robots[j] for j in (i - 1, i + 1) if 0 <= j < len(robots)] for i, r in enumerate(robots)
    }
    plan = LaunchPlan(
        s, 0, robots, tmp / f"relay-{gossip}", mode="realtime", period=PERIOD_S,
        gossip_period=GOSSIP_S, fleet="relay", zenoh_neighbours=neighbours, observe_stacks=True,
        publish_local=False, stack_gossip=gossip,
    )  # fmt: skip
    outcome, _ = _run_launch(plan)
    first_seen: dict[tuple[str, int], dict[str, float]] = {}
    for t, holder, stamps in outcome.collected.stack_log:
        for owner, stamp in stamps.items():
            first_seen.setdefault((owner, stamp), {}).setdefault(holder, t)
    return [
        1e3 * (seen["r4"] - seen["r1"]) / 3
        for (owner, _stamp), seen in first_seen.items()
        if owner == "r1" and "r1" in seen and "r4" in seen
    ]


def run() -> list[Result]:
    _notes.clear()
    rows = gossip_rows()
    with tempfile.TemporaryDirectory() as d:
        rows += _relay_rows(Path(d))
    return rows
