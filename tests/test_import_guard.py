"""The estimator and the protocol are sans-I/O: no event loop, network, threads, clocks or files."""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Mapping
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


# The agent's sans-I/O core: the shell (agents/runtime.py) feeds it events with ``now`` and
# carries out its actions; these files never touch the event loop, network, threads, clocks or
# files (the clocks and the journal reach the core as constructor ports).
PURE_AGENT_FILES = (
    "agents/core.py",
    "agents/node.py",
    "agents/control.py",
    "agents/links.py",
    "agents/gossip.py",
    "agents/rounds.py",
    "agents/sim_radio.py",
    "agents/recovery.py",
    "agents/without_ids.py",
)


def _pure_files(package: str) -> list[Path]:
    if package == "agents":
        return [ROOT / f for f in PURE_AGENT_FILES]
    return _sources(package)


@pytest.mark.parametrize("package", ["estimator", "protocol", "agents"])
def test_pure_packages_import_no_io(package: str) -> None:
    bad = []
    for path in _pure_files(package):
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


# The floors inside deploy/ (docs/architecture.md, "Where things go"): a folder imports only the
# folders below it. base is the floor; study the researchers' runs; operator a real fleet; launch
# local fleets of processes; cli the command line over all of them.
DEPLOY_FLOORS = ("base", "study", "operator", "launch", "cli")
CODE_PACKAGES = (*sorted(ALLOWED_PROJECT_IMPORTS), "bench")


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _project_modules() -> dict[str, Path]:
    return {_module_name(p): p for package in CODE_PACKAGES for p in _sources(package)}


def _resolve(name: str, modules: Mapping[str, Path]) -> str | None:
    """The project module that ``name`` (a module, or a name in one) is, if any."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def _import_graph(modules: Mapping[str, Path]) -> dict[str, set[str]]:
    """Module → the project modules it imports anywhere in its file: at the top, inside a function
    (a lazy import) or under ``TYPE_CHECKING``; ``from a import b`` counts ``a.b`` if that is a
    module."""
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        targets: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            targets |= {t for n in names if (t := _resolve(n, modules)) not in (None, module)}
        graph[module] = targets
    return graph


def _circles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_import_circle_between_files() -> None:
    graph = _import_graph(_project_modules())
    assert "deploy.study.runner" in graph and "agents.core" in graph
    assert _circles(graph) == []


def test_circle_finder_sees_a_lazy_circle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _circles(graph) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_deploy_floors_point_down() -> None:
    """A folder of deploy/ imports only the folders under it; nothing is left at deploy/'s root
    but its ``__init__``."""
    root_files = sorted(p.name for p in (ROOT / "deploy").glob("*.py"))
    assert root_files == ["__init__.py"]
    assert sorted(
        p.name for p in (ROOT / "deploy").iterdir() if p.is_dir() and p.name[0] != "_"
    ) == sorted(DEPLOY_FLOORS)
    bad = []
    for path in _sources("deploy"):
        parts = path.relative_to(ROOT / "deploy").parts
        if len(parts) == 1:
            continue
        floor = DEPLOY_FLOORS.index(parts[0])
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for name, line in _imports(tree):
            bits = name.split(".")
            if bits[0] != "deploy" or len(bits) < 2 or bits[1] not in DEPLOY_FLOORS:
                continue
            if DEPLOY_FLOORS.index(bits[1]) > floor:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name} (a floor above)")
    assert not bad, "\n".join(bad)


def _class_lengths(path: Path) -> list[tuple[str, int, str]]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    return [
        (
            node.name,
            (node.end_lineno or node.lineno) - node.lineno + 1,
            ast.get_docstring(node) or "",
        )
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    ]


def test_agent_core_is_a_dispatcher() -> None:
    """AgentCore dispatches to the policies that own their state (agents/gossip.py,
    agents/rounds.py, agents/sim_radio.py): at most 450 lines."""
    lengths = {name: n for name, n, _ in _class_lengths(ROOT / "agents" / "core.py")}
    assert lengths["AgentCore"] <= 450, lengths["AgentCore"]


def test_no_class_over_500_lines_without_a_reason() -> None:
    bad = [
        f"{path.relative_to(ROOT)}: {name} has {n} lines"
        for package in CODE_PACKAGES
        for path in _sources(package)
        for name, n, doc in _class_lengths(path)
        if n > 500 and "Over 500 lines for a reason:" not in doc
    ]
    assert not bad, "\n".join(bad)


def test_no_other_installed_distribution_ships_our_top_level_names() -> None:
    """docs/architecture.md keeps the packages' top-level names (not ``semfleet.*``) because no
    distribution installed beside semfleet ships them: checked here on this environment."""
    import importlib.metadata

    shipped = importlib.metadata.packages_distributions()
    others = {name: sorted(set(shipped.get(name, [])) - {"semfleet"}) for name in CODE_PACKAGES}
    assert {n: d for n, d in others.items() if d} == {}


def test_plots_and_the_archive_read_value_types_never_a_runner() -> None:
    graph = _import_graph(_project_modules())
    runners = {"deploy.study.runner", "deploy.study.ufastslam", "deploy.study.fleet"}
    for reader in ("deploy.study.plots", "deploy.study.archive", "deploy.study.report"):
        assert not graph[reader] & runners, (reader, graph[reader] & runners)
