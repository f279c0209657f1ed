"""The client package stands alone: what it imports, read from its source (``ast``), and one
import of it in a fresh interpreter where pyarrow and the server's packages cannot be found.

The tools package (``fleethealth_tools``) may use the client and the simulators, never the server.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import textwrap
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLIENT_ROOT = ROOT / "clients" / "python"
CLIENT = "fleethealth_client"
TOOLS = "fleethealth_tools"
SERVER_PACKAGES = {"app", "estimators"}


@dataclass(frozen=True)
class Import:
    """One imported name: the module, the name taken from it (or None), and where."""

    module: str
    name: str | None
    path: Path
    line: int
    at_module_level: bool

    @property
    def top(self) -> str:
        return self.module.partition(".")[0]

    def __str__(self) -> str:
        what = self.module if self.name is None else f"{self.module}.{self.name}"
        return f"{self.path.relative_to(ROOT)}:{self.line} imports {what}"


def _module_name(path: Path, package_dir: Path) -> str:
    parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(package_dir: Path) -> Iterator[Import]:
    """Every import statement of a package, relative imports resolved."""
    for path in sorted(package_dir.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        module_level = {id(node) for node in tree.body}
        this = _module_name(path, package_dir)
        is_package = path.name == "__init__.py"
        for node in ast.walk(tree):
            top_level = id(node) in module_level
            if isinstance(node, ast.Import):
                for alias in node.names:
                    yield Import(alias.name, None, path, node.lineno, top_level)
            elif isinstance(node, ast.ImportFrom):
                module = node.module or ""
                if node.level:
                    base = this.split(".")
                    base = base if is_package else base[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    module = ".".join([*base, module] if module else base)
                for alias in node.names:
                    yield Import(module, alias.name, path, node.lineno, top_level)


def _distribution_imports(requirements: list[str]) -> set[str]:
    """Import names of requirement strings (``websockets>=13`` -> ``websockets``)."""
    names = set()
    for requirement in requirements:
        match = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", requirement)
        assert match is not None, requirement
        names.add(match.group(0).lower().replace("-", "_"))
    return names


def _client_project() -> dict:  # type: ignore[type-arg]
    return tomllib.loads((CLIENT_ROOT / "pyproject.toml").read_text())["project"]


def test_client_imports_only_stdlib_and_its_declared_dependencies() -> None:
    project = _client_project()
    required = _distribution_imports(project["dependencies"])
    optional = _distribution_imports(
        [req for reqs in project.get("optional-dependencies", {}).values() for req in reqs]
    )
    allowed = set(sys.stdlib_module_names) | required | optional | {CLIENT}
    found = list(imports_of(CLIENT_ROOT / CLIENT))
    assert found, "no imports found: wrong folder?"
    undeclared = [str(i) for i in found if i.top not in allowed]
    assert undeclared == [], "imports neither stdlib nor declared in clients/python/pyproject.toml"
    server = [str(i) for i in found if i.top in SERVER_PACKAGES | {TOOLS}]
    assert server == []
    # An optional dependency is imported where it is used, so the package imports without it.
    eager = [str(i) for i in found if i.top in optional and i.at_module_level]
    assert eager == [], "optional dependencies imported at module level"


@pytest.mark.parametrize("package", [CLIENT, TOOLS])
def test_no_private_name_crosses_a_module(package: str) -> None:
    """A name starting with ``_`` stays in its module: what two modules share has a public home."""
    package_dir = CLIENT_ROOT / CLIENT if package == CLIENT else ROOT / TOOLS
    crossing = [
        str(i)
        for i in imports_of(package_dir)
        if i.top in {CLIENT, TOOLS}
        and (
            any(part.startswith("_") for part in i.module.split("."))
            or (i.name is not None and i.name.startswith("_"))
        )
    ]
    assert crossing == []


def test_tools_use_the_client_not_the_server() -> None:
    found = list(imports_of(ROOT / TOOLS))
    assert any(i.top == CLIENT for i in found)
    assert [str(i) for i in found if i.top == "app"] == []


def test_server_never_imports_the_client() -> None:
    """The server speaks HTTP; it does not call itself through the client package."""
    found = [str(i) for i in imports_of(ROOT / "app") if i.top == CLIENT]
    assert found == []


BLOCKED = ("pyarrow", "app", "estimators", TOOLS)
# Runs in a fresh interpreter: a finder refuses the blocked packages, as if not installed.
_ALONE = textwrap.dedent(
    f"""
    import importlib, pkgutil, sys

    BLOCKED = {BLOCKED!r}

    class Refuse:
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
            return None

    sys.meta_path.insert(0, Refuse())
    import fleethealth_client
    for info in pkgutil.walk_packages(fleethealth_client.__path__, "fleethealth_client."):
        importlib.import_module(info.name)
    from fleethealth_client import FleetHealthClient, encode_batch, encode_frame

    # Building a client opens its HTTP connection pool: only the client's own dependencies.
    with FleetHealthClient("http://127.0.0.1:1/", "key") as client:
        assert client._core.base_url == "http://127.0.0.1:1"
    batch = encode_batch("json", "b-1", {{"current": [1.0, float("nan")]}}, t_s=[0.0, 0.01])
    assert batch.content.endswith(b'"channels":{{"current":[1.0,null]}}}}'), batch.content
    assert encode_frame(1, {{"current": [1.0]}}, t_s=[0.0]).startswith('{{"type":"samples"')
    for fmt in ("arrow", "csv"):
        try:
            encode_batch(fmt, "b-1", {{"current": [1.0]}}, t_s=[0.0])
        except ImportError as exc:
            print(fmt, exc)
        else:
            raise SystemExit(f"{{fmt}} encoded without pyarrow")
    loaded = sorted({{m.partition(".")[0] for m in sys.modules}} & set(BLOCKED))
    print("loaded:", loaded)
    """
)


def test_client_imports_and_encodes_json_without_pyarrow_or_the_server(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(CLIENT_ROOT)}
    done = subprocess.run(
        [sys.executable, "-c", _ALONE],
        cwd=tmp_path,  # not the repository root, whose packages would be importable from ''
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[-1] == "loaded: []"
    for fmt, line in zip(("arrow", "csv"), lines[:2], strict=True):
        assert line.startswith(f"{fmt} ") and 'pip install "fleethealth-client[arrow]"' in line
