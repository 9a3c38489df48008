"""The live table of a launch: its title and its rows tell the same step, to the very end."""

from __future__ import annotations

import asyncio
import io
import re
from pathlib import Path

from rich.console import Console

from deploy.launch import Launcher, LaunchPlan, launch
from deploy.launch.conductor import Conductor
from deploy.launch.table import progress_table
from sim.loader import parse_scenario
from tests.deploy.test_launch import world_text

STEPS = 3


def test_realtime_table_ends_with_every_robot_at_the_last_step(tmp_path: Path) -> None:
    """Realtime: the last frame goes out before the agents step on it. The table shown at the
    end is the one after the last estimates came in: ``step 3/3`` over rows that say 3 (it
    used to say ``step 3/3`` over rows that said 2)."""
    text = world_text("pair", 2, 3.0, STEPS, 0.1)
    scenario = parse_scenario(text, "pair.toml")
    plan = LaunchPlan(scenario, 0, ["r1", "r2"], tmp_path, mode="realtime", period=0.2)
    screen = io.StringIO()
    launch(plan, console=Console(file=screen, width=200, force_terminal=False))
    out = screen.getvalue()
    assert out.count(f"step {STEPS}/{STEPS}") == 1, out  # the final table, printed once
    rows = re.findall(r"^(r\d)\s+(yes|no)\s+(\d+)\s", out, re.MULTILINE)
    assert sorted(rows) == [("r1", "yes", str(STEPS)), ("r2", "yes", str(STEPS))], out


def test_table_title_is_the_step_its_rows_show_while_frames_run_ahead(tmp_path: Path) -> None:
    """Mid-run the conductor has sent frame k while the agents still estimate k − 1: the title
    says what every row has reached, not how many frames went out."""
    scenario = parse_scenario(world_text("pair", 2, 3.0, STEPS, 0.1), "pair.toml")
    plan = LaunchPlan(scenario, 0, ["r1", "r2"], tmp_path, mode="realtime", period=0.2)
    launcher = Launcher(plan)
    seen: list[tuple[int, str, list[int]]] = []

    def on_step(conductor: Conductor, k: int) -> None:
        table = progress_table(conductor, plan.robots, STEPS)
        steps = [int(row[2]) for row in table.rows]
        seen.append((conductor.k, str(table.title), steps))

    asyncio.run(launcher.run(on_step))
    assert len(seen) == STEPS
    assert any(sent > min(steps) for sent, _, steps in seen), seen  # frames did run ahead
    for _, title, steps in seen:
        assert title == f"step {min(steps)}/{STEPS}", seen
