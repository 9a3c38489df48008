"""The scenario options every command that reads a world shares."""

from __future__ import annotations

import argparse
import tomllib
from typing import Any

from sim.loader import load_scenario
from sim.scenario import Scenario, ScenarioError


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments every command that reads a scenario shares."""
    p.add_argument("scenario", help="a scenario file (.toml) or a bundled name such as 'paper'")
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME",
        help="apply a variant defined in the file (repeatable), e.g. sense10, comm10",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        dest="overrides",
        help="override a field, e.g. --set sensor.range=10 (repeatable; TOML values)",
    )


def parse_override(text: str) -> tuple[str, Any]:
    """``FIELD=VALUE`` → (field, value); VALUE is read as a TOML value, else kept as a string."""
    field, sep, value = text.partition("=")
    if not sep or not field.strip():
        raise ScenarioError(f"--set {text!r}: expected FIELD=VALUE, e.g. sensor.range=10")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    return field.strip(), parsed


def scenario_from_args(args: argparse.Namespace) -> Scenario:
    overrides = dict(parse_override(t) for t in args.overrides)
    return load_scenario(args.scenario, args.variant, overrides)
