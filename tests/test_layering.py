"""Imports point down: a module imports only from its own layer or the layers below it.

Every module's imports are read from its source (``ast``, lazy imports inside functions and
``TYPE_CHECKING`` blocks included), so the test needs nothing imported and sees what a reader
sees. docs/architecture.md draws the same layers.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The layers of service/, bottom up; a module belongs to the layer of its longest listed prefix.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "base",
        (
            "service",  # the package itself: __version__
            "service.argtypes",
            "service.jit",
            "service.config",
            "service.mesh",
            "service.meshfile",
            "service.phantoms",
            "service.scene",
            "service.forward",
            "service.spare",
            "service.sendwait",
            "service.folders",
            "service.sparse_libs",
            "service.material_range",
            "service.network_size",
            "service.started",
        ),
    ),
    ("fem", ("service.fem",)),
    ("surrogate", ("service.surrogate",)),
    ("registration", ("service.registration", "service.synthetic")),
    ("store", ("service.store",)),
    ("build, bench", ("service.build", "service.warmup", "service.bench")),
    ("api", ("service.api",)),
    ("apps", ("service.cli", "service.commands", "service.demo", "service.loadtest", "service.igtl")),
)
#: The only layer that may use the client package (to drive a server it starts).
CLIENT_USERS = "apps"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules(package: str) -> dict[str, Path]:
    return {module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}


def is_module(name: str) -> bool:
    path = ROOT.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imports(name: str, path: Path) -> set[str]:
    """The project modules `name` imports (relative imports resolved; ``from a import b`` is
    a.b where b is a module, else a)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                found.add(sub if is_module(sub) else source)
    return {m for m in found if m.split(".")[0] in ("service", "clients")}


def layer_of(name: str) -> int | None:
    best, layer = -1, None
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (name == prefix or name.startswith(prefix + ".")) and len(prefix) > best:
                best, layer = len(prefix), i
    return layer


SERVICE = modules("service")
CLIENTS = modules("clients")


def test_every_module_has_a_layer():
    """A new module must be placed (here and in docs/architecture.md) before it can be checked."""
    unplaced = sorted(name for name in SERVICE if layer_of(name) is None)
    assert not unplaced, f"place these modules in a layer of tests/test_layering.py: {unplaced}"


@pytest.mark.parametrize("name", sorted(SERVICE))
def test_service_imports_point_down(name):
    here = layer_of(name)
    if here is None:
        pytest.fail(f"{name} has no layer (see test_every_module_has_a_layer)")
    upward = []
    for target in sorted(imports(name, SERVICE[name])):
        if target.startswith("clients"):
            if LAYERS[here][0] != CLIENT_USERS:
                upward.append(f"{target} (only the {CLIENT_USERS} layer may use the client)")
            continue
        there = layer_of(target)
        if there is not None and there > here:
            upward.append(f"{target} ({LAYERS[there][0]})")
    assert not upward, f"{name} ({LAYERS[here][0]}) imports from a higher layer: {upward}"


@pytest.mark.parametrize("name", sorted(CLIENTS))
def test_clients_import_nothing_from_service(name):
    """A client needs only the clients package (and its own dependencies)."""
    used = sorted(m for m in imports(name, CLIENTS[name]) if m.split(".")[0] == "service")
    assert not used, f"{name} imports the service: {used}"


def test_the_reader_sees_every_kind_of_import(tmp_path):
    """The parser itself: plain, from, relative, lazy and TYPE_CHECKING imports all count."""
    source = (
        "import service.fem.model\n"
        "from typing import TYPE_CHECKING\n"
        "from .. import store\n"
        "from ..api import schemas\n"
        "from . import engine\n"
        "if TYPE_CHECKING:\n"
        "    from clients.client import Client\n"
        "def f():\n"
        "    from ..bench.report import main\n"
    )
    probe = tmp_path / "probe.py"  # read as if it were service/registration/probe.py
    probe.write_text(source)
    found = imports("service.registration.probe", probe)
    assert found == {
        "service.fem.model",
        "service.store",
        "service.api.schemas",
        "service.registration.engine",
        "clients.client",
        "service.bench.report",
    }


def test_the_architecture_page_names_every_module():
    """docs/architecture.md gives each module a line: a new one is described where it is placed."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    missing = []
    for path in SERVICE.values():
        rel = path.relative_to(ROOT / "service")
        if (
            rel.name == "__init__.py"
            or rel.parts[0] == "bench"
            or rel.parts[:2] == ("scene", "shipped")
            or "routes" in rel.parts
        ):
            continue  # packages described as a whole
        if f"`{rel.as_posix()}`" not in page:
            missing.append(rel.as_posix())
    assert not missing, f"docs/architecture.md has no line for: {missing}"
