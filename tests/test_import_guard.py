"""The estimator and the protocol are sans-I/O: no event loop, network, threads, clocks or files."""

from __future__ import annotations

import ast
import subprocess
import sys
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


def _modules(package: str) -> list[str]:
    return [
        ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for path in _sources(package)
    ]


def _loads_gtsam(modules: list[str]) -> list[str]:
    """The modules among ``modules`` that load gtsam, each imported in a fresh interpreter (an
    earlier import in this process would hide it)."""
    probe = (
        "import importlib, sys; importlib.import_module(sys.argv[1]); print('gtsam' in sys.modules)"
    )
    bad = []
    for name in modules:
        done = subprocess.run(
            [sys.executable, "-c", probe, name],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        )
        if done.stdout.strip() != "False":
            bad.append(name)
    return bad


def test_protocol_imports_no_gtsam() -> None:
    """protocol/ depends on estimator/ for plain data types only (ARCHITECTURE.md): a peer that
    merely decodes stacks, frames or estimates needs no GTSAM."""
    modules = _modules("protocol")
    assert "protocol.estimate" in modules
    assert _loads_gtsam(modules) == []


def test_gtsam_probe_sees_a_gtsam_import() -> None:
    assert _loads_gtsam(["estimator.summary", "estimator.hybrid"]) == ["estimator.hybrid"]
