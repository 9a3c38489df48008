"""Issue 14's bytes target: bytes sent per agent per step with delta gossip against full stacks,
measured in the same run (realtime launches of the paper scenario and of a generated 10-robot
world; every stack an agent published — after its steps, answers to digests, gossip ticks —
counted from its counters). Target: full/delta ≥ 5, for the default (``stack_gossip = "ask"``,
delta gossip whose robots ask a relay for the slots of the robots they do not hear; docs/wire.md,
"Asks") and for ``"delta"`` (no asks), in the same run.
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
        for gossip, what in (
            ("ask", "delta gossip with asks, the default"),
            ("delta", 'delta gossip without asks ("delta")'),
        ):
            ratio = per_step["full"] / max(per_step[gossip], 1e-9)
            met = "met" if ratio >= TARGET_BYTES_RATIO else "NOT met"
            rows.append(
                Result(
                    f'bytes per agent per step, "{gossip}" vs full gossip ({name})',
                    len(s.robot_ids),
                    per_step[gossip],
                    baseline_ms=per_step["full"],
                    note=f"figures are kB per agent per step, not ms: {what} "
                    f"{per_step[gossip]:.1f} kB, full {per_step['full']:.1f} kB, full/{gossip} "
                    f"{ratio:.1f} (target ≥ {TARGET_BYTES_RATIO:g}) {met}; realtime, {steps} "
                    f"steps at {PERIOD_S:g} s, gossip every {GOSSIP_S:g} s, same run",
                )
            )
    return rows


def run() -> list[Result]:
    with tempfile.TemporaryDirectory() as d:
        return _bytes_rows(Path(d))
