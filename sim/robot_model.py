"""Robot model files: what a robot knows of itself without any world (docs/scenarios.md).

A model file holds ``format`` and a scenario's ``[classes]``, ``[classifier]``, ``[noise]`` and
``[sensor]`` tables, read and written by the very code that reads and writes them in a scenario;
errors are :class:`ScenarioError` naming the file and field, e.g.
``model.toml: classifier.noise_std: -1.0 must be > 0``.
"""

from __future__ import annotations

from pathlib import Path

from sim.generate import model_tables
from sim.loader import (
    MODEL_TABLES,
    FieldReader,
    check_format,
    parse_toml,
    read_file,
    robot_model_tables,
)
from sim.scenario import FORMAT_VERSION, RobotModel

__all__ = ["RobotModel", "dump_robot_model", "load_robot_model", "parse_robot_model"]


def load_robot_model(path: str | Path) -> RobotModel:
    """Read and validate the robot model file ``path``."""
    path = Path(path)
    return parse_robot_model(read_file(path, "robot model file"), str(path), path.parent)


def parse_robot_model(text: str, label: str = "<string>", folder: Path | None = None) -> RobotModel:
    """Validate TOML text into a :class:`RobotModel`; ``label`` names the file in errors;
    relative file paths (``classifier.file``) are relative to ``folder`` (None: the current
    folder)."""
    top = FieldReader(label, parse_toml(text, label), "")
    check_format(top)
    top.check_keys({"format", *MODEL_TABLES})
    return robot_model_tables(top, "model", folder)


def dump_robot_model(model: RobotModel) -> str:
    """TOML text that :func:`parse_robot_model` reads back into ``model``."""
    return "\n".join([f"format = {FORMAT_VERSION}", "", *model_tables(model)]) + "\n"
