"""The suite's own bookkeeping: the serial list of tests/conftest.py names real modules, and
`make test` runs both of its phases."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import HERE, LONGEST_FIRST, SERIAL_MODULES, dealt, worker_chunks


def test_the_modules_conftest_names_exist() -> None:
    for name, modules in (("SERIAL_MODULES", SERIAL_MODULES), ("LONGEST_FIRST", LONGEST_FIRST)):
        missing = sorted(m for m in modules if not (HERE / m).is_file())
        assert not missing, f"{name} names modules that are gone: {missing}"


def test_the_longest_modules_head_the_chunk_each_worker_gets_first() -> None:
    # Tests of modules a (longest) … e, then short ones s; two workers get chunks of 10 and 11.
    modules = ["s"] * 4 + ["b"] * 2 + ["a"] * 3 + ["c", "d", "e"] + ["s"] * 9
    assert worker_chunks(len(modules), 2) == [10, 11]
    assert worker_chunks(7, 3) == [2, 2, 3]
    order = dealt(modules, ("a", "b", "c", "d", "e"), 2)
    assert sorted(order) == list(range(len(modules)))  # a permutation
    first, second = [modules[i] for i in order[:10]], [modules[i] for i in order[10:]]
    assert first[:5] == ["a", "a", "a", "d", "e"] and set(first[5:]) == {"s"}  # 1st, 4th, 5th
    assert second[:3] == ["b", "b", "c"] and set(second[3:]) == {"s"}  # 2nd, 3rd
    assert [i for i in order if modules[i] == "s"] == [i for i, m in enumerate(modules) if m == "s"]
    one = [modules[i] for i in dealt(modules, ("a", "b", "c", "d", "e"), 1)]
    assert one == ["a"] * 3 + ["b"] * 2 + ["c", "d", "e"] + ["s"] * 13


def test_make_test_runs_the_parallel_and_the_serial_phase() -> None:
    makefile = (Path(HERE).parent / "Makefile").read_text(encoding="utf-8")
    recipe = makefile.split("\ntest: ", 1)[1].split("\n\n", 1)[0]
    assert '-m "not serial"' in recipe and "-m serial" in recipe, recipe


def test_every_module_over_300_lines_says_why() -> None:
    """Issue 12: no module over 300 lines without a reason in its docstring."""
    root = Path(HERE).parent
    silent = []
    for package in ("estimator", "protocol", "sim", "agents", "deploy", "bench"):
        for path in sorted((root / package).rglob("*.py")):
            text = path.read_text(encoding="utf-8")
            if len(text.splitlines()) > 300:
                doc = ast.get_docstring(ast.parse(text)) or ""
                if "Over 300 lines for a reason:" not in doc:
                    silent.append(str(path.relative_to(root)))
    assert not silent, f"over 300 lines with no reason in the docstring: {silent}"
