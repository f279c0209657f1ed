"""Where things live: SQL only in repositories, and the statuses the API names."""

from __future__ import annotations

import ast
from pathlib import Path

from app.status import HealthStatus
from estimators.base import STATUSES

APP = Path(__file__).resolve().parents[2] / "app"
SQL_CONSTRUCTS = frozenset({"select", "insert", "update", "delete", "text"})
# Files allowed to build SQL: repositories, the ORM tables and the migrations.
ALLOWED = ("repository.py", "models.py")


def _sql_uses(tree: ast.AST) -> list[tuple[int, str]]:
    """Lines that import a SQL construct from SQLAlchemy, or call one through the module."""
    found: list[tuple[int, str]] = []
    module_aliases: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "sqlalchemy":
            found += [(node.lineno, a.name) for a in node.names if a.name in SQL_CONSTRUCTS]
        elif isinstance(node, ast.Import):
            module_aliases |= {a.asname or a.name for a in node.names if a.name.split(".")[0] == "sqlalchemy"}
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in SQL_CONSTRUCTS
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id in module_aliases
        ):
            found.append((node.lineno, f"{node.func.value.id}.{node.func.attr}"))
    return found


def _app_sources() -> list[Path]:
    return [
        p
        for p in sorted(APP.rglob("*.py"))
        if "migrations" not in p.relative_to(APP).parts and p.name not in ALLOWED
    ]


def test_sql_lives_in_repositories_only() -> None:
    offenders = [
        f"{p.relative_to(APP.parent)}:{line}: {name}"
        for p in _app_sources()
        for line, name in _sql_uses(ast.parse(p.read_text(), str(p)))
    ]
    assert offenders == [], "SQL outside repositories:\n" + "\n".join(offenders)


def test_the_check_finds_sql_where_it_is() -> None:
    # The detector itself: it must flag both spellings, and the repositories do hold SQL.
    assert _sql_uses(ast.parse("from sqlalchemy import select, func\nselect(1)")) == [(1, "select")]
    assert _sql_uses(ast.parse("import sqlalchemy as sa\nsa.update(x)")) == [(2, "sa.update")]
    assert _sql_uses(ast.parse("d = {}\nd.update(a=1)\nws.send_text('x')")) == []
    repos = sorted(APP.rglob("repository.py"))
    assert len(repos) >= 6 and all(_sql_uses(ast.parse(p.read_text())) for p in repos)
    assert len(_app_sources()) > 20


def test_api_statuses_are_the_estimators_statuses() -> None:
    assert [s.value for s in HealthStatus] == list(STATUSES)
