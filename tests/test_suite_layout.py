"""The suite's own bookkeeping: the serial list of tests/conftest.py names real modules, and
`make test` runs both of its phases."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import HERE, SERIAL_MODULES


def test_serial_modules_exist() -> None:
    missing = sorted(m for m in SERIAL_MODULES if not (HERE / m).is_file())
    assert not missing, f"SERIAL_MODULES names modules that are gone: {missing}"


def test_make_test_runs_the_parallel_and_the_serial_phase() -> None:
    makefile = (Path(HERE).parent / "Makefile").read_text(encoding="utf-8")
    recipe = makefile.split("\ntest: ", 1)[1].split("\n\n", 1)[0]
    assert '-m "not serial"' in recipe and "-m serial" in recipe, recipe
