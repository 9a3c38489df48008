"""Every `semfleet` command shown in README.md and docs/ matches the code.

A command in the text or a table, or a command line with placeholders (``ID``, ``FILE``,
``[--steps N]``, ``a|b``, ``…``, ``$r``), is a synopsis: its command must exist and every option
it names must be one of that command's. A command line of a code block without them is an
example and is run, in a scratch folder, with small sizes (:data:`SMALL`): it must succeed.
Examples that need running agents or take minutes are run by the test named in
:data:`RUN_ELSEWHERE`, which must exist.
"""

from __future__ import annotations

import argparse
import ast
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

from deploy.cli.main import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# Small sizes for examples: (pattern, replacement), applied in order.
SMALL = (
    (r"--runs \d+", "--runs 1"),
    (r"--jobs \d+", "--jobs 1"),
    (r"--particles \d+", "--particles 8"),
    (r"--samples \d+", "--samples 100"),
    # the paper's 60 steps: 18 instead, unless the example compares with the paper's figures,
    # which only the paper world has (--paper: one run of it)
    (r"--scenario paper\b(?!.*--paper\b)", "--scenario lanes:short"),
)

# Examples whose run needs agents, a fleet or minutes: the test that runs them exactly.
RUN_ELSEWHERE = {
    "semfleet demo": (
        "tests/deploy/test_cli.py::"
        "test_demo_launches_three_agents_over_zenoh_and_prints_the_final_table"
    ),
}
# Whole files whose examples are a walk-through run as one test.
FILES_RUN_ELSEWHERE = {
    "docs/robots.md": (
        "tests/deploy/test_fleet_from_logs.py::"
        "test_three_agents_fed_only_by_replayed_logs_gossip_fuse_and_finish"
    ),
}

_PLACEHOLDER = re.compile(r"(^|[\s=/:,|\[])([A-Z][A-Z0-9_]*)(?=$|[\s|\]:,.@-])")


@dataclass(frozen=True)
class Shown:
    doc: str
    line: int
    text: str
    fenced: bool  # a line of a code block (else a code span in the text: a reference)

    def __str__(self) -> str:
        return f"{self.doc}:{self.line}: {self.text}"

    @property
    def synopsis(self) -> bool:
        """Not a command to run as it stands: placeholders, or a reference in the text."""
        t = self.text
        if not self.fenced:
            return True
        return bool(
            any(c in t for c in "[|…$&") or "..." in t or _PLACEHOLDER.search(t.split("#")[0])
        )


def shown_commands() -> list[Shown]:
    """`semfleet …` lines of fenced code blocks (continuations joined, comments dropped) and
    `semfleet …` code spans in the text and tables."""
    found: list[Shown] = []
    for path in DOCS:
        doc = str(path.relative_to(ROOT))
        lines = path.read_text(encoding="utf-8").splitlines()
        fenced = False
        i = 0
        while i < len(lines):
            line = lines[i]
            if line.lstrip().startswith("```"):
                fenced = not fenced
            elif fenced and line.strip().startswith("semfleet "):
                start, text = i + 1, line.strip()
                while text.endswith("\\") and i + 1 < len(lines):
                    i += 1
                    text = text[:-1].rstrip() + " " + lines[i].strip()
                text = _drop_comment(text)
                found.append(Shown(doc, start, text, fenced=True))
            elif not fenced:
                for span in re.findall(r"`(semfleet [^`]+)`", line):
                    found.append(Shown(doc, i + 1, span.replace("\\|", "|"), fenced=False))
            i += 1
    return found


def _drop_comment(text: str) -> str:
    return re.sub(r"\s+#\s.*$", "", text).strip()


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings}


def command_parsers(text: str) -> list[argparse.ArgumentParser]:
    """The parsers of the (sub)command a line names: ``fleet status|watch`` gives two."""
    words = text.split()[1:]
    parsers = [build_parser()]
    while words and _subparsers(parsers[0]):
        names = words.pop(0).split("|")
        subs = _subparsers(parsers[0])
        unknown = [n for n in names if n not in subs]
        assert not unknown, f"no command {unknown} (has {sorted(subs)})"
        parsers = [subs[n] for n in names]
    return parsers


SHOWN = shown_commands()
EXAMPLES = [s for s in SHOWN if not s.synopsis]


def test_the_docs_show_commands_at_all() -> None:
    assert len(SHOWN) >= 30 and len(EXAMPLES) >= 10, [str(s) for s in SHOWN]
    assert {s.doc for s in SHOWN} >= {"README.md", "docs/agents.md", "docs/scenarios.md"}


@pytest.mark.parametrize("shown", SHOWN, ids=str)
def test_every_shown_command_and_option_exists(shown: Shown) -> None:
    parsers = command_parsers(shown.text)
    options = set().union(*(_options(p) for p in parsers))
    named = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*|-[a-z])\b", shown.text))
    assert named <= options, f"{shown}: no option {sorted(named - options)}"


def test_examples_run_elsewhere_are_run_by_tests_that_exist() -> None:
    for node in (*RUN_ELSEWHERE.values(), *FILES_RUN_ELSEWHERE.values()):
        file, name = node.split("::")
        tree = ast.parse((ROOT / file).read_text(encoding="utf-8"))
        assert name in {f.name for f in ast.walk(tree) if isinstance(f, ast.FunctionDef)}, node
    shown_texts = {s.text for s in EXAMPLES}
    assert set(RUN_ELSEWHERE) <= shown_texts, "a command listed as run elsewhere is not shown"


def _small(text: str) -> list[str]:
    for pattern, replacement in SMALL:
        text = re.sub(pattern, replacement, text)
    return shlex.split(text)[1:]


def _run_order(examples: list[Shown]) -> list[Shown]:
    """Examples that write a file (``scenario generate``, ``scenario model``) first, so those
    that read it find it, whatever order the page shows them in."""
    return sorted(examples, key=lambda s: " generate " not in s.text and " model " not in s.text)


EXAMPLES_HERE = [
    s for s in EXAMPLES if s.text not in RUN_ELSEWHERE and s.doc not in FILES_RUN_ELSEWHERE
]


@pytest.mark.parametrize("doc", sorted({s.doc for s in EXAMPLES_HERE}))
def test_examples_run_with_small_sizes(
    doc: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    for shown in _run_order([s for s in EXAMPLES_HERE if s.doc == doc]):
        argv = _small(shown.text)
        assert main(argv) == 0, f"{shown} (run as {shlex.join(argv)})"
