"""The estimator and the protocol are sans-I/O: no event loop, network, threads, clocks or files."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN_MODULES = {
    "asyncio",
    "zenoh",
    "socket",
    "threading",
    "time",
    "subprocess",
    "multiprocessing",
}
FORBIDDEN_CALLS = {"open"}
# Import direction (ARCHITECTURE.md): what each package may import from the project.
ALLOWED_PROJECT_IMPORTS = {
    "estimator": {"estimator"},
    "protocol": {"protocol", "estimator"},
    "sim": {"sim", "estimator"},
    "agents": {"agents", "protocol", "estimator"},
    "deploy": {"deploy", "agents", "protocol", "estimator", "sim"},
}
PROJECT = set(ALLOWED_PROJECT_IMPORTS)
ZENOH_MODULE = "agents/transport/zenoh_transport.py"  # the only module that imports zenoh


def _imports(tree: ast.AST) -> list[tuple[str, int]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, node.lineno))
    return out


def _sources(package: str) -> list[Path]:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no Python files found in {package}/"
    return files


@pytest.mark.parametrize("package", ["estimator", "protocol"])
def test_pure_packages_import_no_io(package: str) -> None:
    bad = []
    for path in _sources(package):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for name, line in _imports(tree):
            if name.split(".")[0] in FORBIDDEN_MODULES:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in FORBIDDEN_CALLS
            ):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} calls {node.func.id}()")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("package", sorted(ALLOWED_PROJECT_IMPORTS))
def test_imports_point_downwards(package: str) -> None:
    allowed = ALLOWED_PROJECT_IMPORTS[package]
    bad = []
    for path in _sources(package):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for name, line in _imports(tree):
            top = name.split(".")[0]
            if top in PROJECT and top not in allowed:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
            if package == "sim" and top == "estimator" and not name.startswith("estimator.models"):
                bad.append(
                    f"{path.relative_to(ROOT)}:{line} imports {name} (sim: estimator.models only)"
                )
            if top == "zenoh" and path.relative_to(ROOT).as_posix() != ZENOH_MODULE:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports zenoh outside the transport")
    assert not bad, "\n".join(bad)


def test_import_guard_catches_a_forbidden_import(tmp_path: Path) -> None:
    tree = ast.parse("import time\nfrom asyncio import sleep\n")
    assert [n for n, _ in _imports(tree)] == ["time", "asyncio"]
