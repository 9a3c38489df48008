"""Issue 14's bytes target: bytes sent per agent per step with delta gossip against full stacks,
measured in the same run (realtime launches of the paper scenario and of a generated 10-robot
world; every stack an agent published — after its steps, answers to digests, gossip ticks —
counted from its counters). Target: full/delta ≥ 5. Also measured, not a target: the bytes of
``stack_gossip = "ask"`` (docs/wire.md, "Asks"), which relays every version of a robot out of
range at once.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from bench import Result
from bench.bench_agents import GOSSIP_S, PERIOD_S, _run_launch
from deploy.launch import LaunchPlan
from sim.generate import dump_scenario, generate_scenario
from sim.loader import load_scenario, parse_scenario


def notes() -> list[str]:
    return []


TARGET_BYTES_RATIO = 5.0  # issue 14: delta gossip sends ≥ 5× fewer bytes per agent per step


def _bytes_rows(tmp: Path) -> list[Result]:
    """Bytes sent per agent per step, full stacks against delta gossip, in the same run: the
    paper scenario and a generated 10-robot world, realtime, every stack an agent published
    (after its steps, answers to digests, and gossip ticks) counted."""
    worlds = [("paper", load_scenario("paper"))]
    gen = generate_scenario(10, 30, 3, seed=11, steps=20)
    path = tmp / "gen10.toml"
    path.write_text(dump_scenario(gen), encoding="utf-8")
    worlds.append(
        ("generated 10 robots", parse_scenario(path.read_text(encoding="utf-8"), str(path)))
    )
    rows = []
    for name, s in worlds:
        per_step = {}
        steps = min(s.steps, 20)
        for gossip in ("full", "delta", "ask"):
            plan = LaunchPlan(
                s, 0, list(s.robot_ids), tmp / f"bytes-{gossip}-{len(s.robot_ids)}",
                mode="realtime", period=PERIOD_S, gossip_period=GOSSIP_S, steps=steps,
                fleet="bytes", publish_local=False, stack_gossip=gossip,
            )  # fmt: skip
            outcome, _ = _run_launch(plan)
            counters = outcome.collected.counters.values()
            sent = sum(c.get("bytes_sent", 0) + c.get("bytes_sent_ticks", 0) for c in counters)
            per_step[gossip] = sent / (len(s.robot_ids) * steps) / 1e3
        ratio = per_step["full"] / max(per_step["delta"], 1e-9)
        met = "met" if ratio >= TARGET_BYTES_RATIO else "NOT met"
        rows.append(
            Result(
                f"bytes per agent per step, delta vs full gossip ({name})",
                len(s.robot_ids),
                per_step["delta"],
                baseline_ms=per_step["full"],
                note=f"figures are kB per agent per step, not ms: delta {per_step['delta']:.1f} "
                f"kB, full {per_step['full']:.1f} kB, full/delta {ratio:.1f} (target ≥ "
                f"{TARGET_BYTES_RATIO:g}) {met}; realtime, {steps} steps at {PERIOD_S:g} s, "
                f"gossip every {GOSSIP_S:g} s, same run",
            )
        )
        asked = per_step["full"] / max(per_step["ask"], 1e-9)
        rows.append(
            Result(
                f'bytes per agent per step, stack_gossip = "ask" vs full gossip ({name})',
                len(s.robot_ids),
                per_step["ask"],
                baseline_ms=per_step["full"],
                note=f"kB, as above: ask {per_step['ask']:.1f} kB, full/ask {asked:.1f}; every "
                f'version of a robot out of range pushed by one relay (docs/wire.md, "Asks"); '
                f"not a target",
            )
        )
    return rows


def run() -> list[Result]:
    with tempfile.TemporaryDirectory() as d:
        return _bytes_rows(Path(d))
