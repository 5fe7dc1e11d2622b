"""Cache keys derived from the code: a stage recomputes when its source (or a module it uses)
or a numerical library changes, without hand-written version strings.

``code_key("stages.radius")`` hashes the source of that module and of every project module it
imports, transitively (imports of ``pipeline`` and ``stages`` found in the syntax tree, including
those inside functions but not those under ``if TYPE_CHECKING:``; the data folders of the
packages met, e.g. the report's templates), together with the installed versions of the
numerical libraries.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
from collections.abc import Iterator
from functools import cache
from importlib import metadata
from pathlib import Path

PROJECT_PACKAGES = ("pipeline", "stages")
LIBRARIES = ("numpy", "scipy", "cvxpy", "clarabel", "sympy", "numba", "shapely", "control")


@cache
def _package_root(package: str) -> Path:
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"project package {package!r} not found")
    return Path(next(iter(spec.submodule_search_locations)))


def module_file(module: str) -> Path | None:
    """The source file of a project module (``a.b`` -> ``a/b.py`` or ``a/b/__init__.py``)."""
    top, *rest = module.split(".")
    if top not in PROJECT_PACKAGES:
        return None
    base = _package_root(top).joinpath(*rest)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


# the nodes that hold statements: an import is a statement, never inside an expression
_STATEMENT_HOLDERS = (ast.stmt, ast.excepthandler, ast.match_case)


def _runtime_nodes(tree: ast.AST) -> Iterator[ast.AST]:
    """Every statement of ``tree`` except those in the bodies of ``if TYPE_CHECKING:`` (never
    run). Expressions are not entered (a tenth of the nodes: ~0.2 s less per process)."""
    pending = [tree]
    while pending:
        node = pending.pop()
        yield node
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            pending.extend(node.orelse)
            continue
        pending.extend(
            child for child in ast.iter_child_nodes(node) if isinstance(child, _STATEMENT_HOLDERS)
        )


@cache  # each stage's key parses the modules it shares with the others: once per source
def _imported(module: str, source: str, is_package: bool) -> frozenset[str]:
    """Project modules named by the imports in ``source`` (and their parent packages) that run:
    imports under ``if TYPE_CHECKING:`` only name types for the checker."""
    names: set[str] = set()
    package = module if is_package else module.rpartition(".")[0]
    for node in _runtime_nodes(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)  # submodules
    found = set()
    for name in names:
        parts = name.split(".")
        for end in range(1, len(parts) + 1):  # importing a.b.c runs a and a.b too
            prefix = ".".join(parts[:end])
            if module_file(prefix) is not None:
                found.add(prefix)
    return frozenset(found)


@cache
def library_versions() -> tuple[tuple[str, str], ...]:
    """``(name, version)`` of each numerical library (``"absent"`` if not installed)."""
    versions = []
    for name in LIBRARIES:
        try:
            versions.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:
            versions.append((name, "absent"))
    return tuple(versions)


def _sources(modules: tuple[str, ...]) -> dict[str, bytes]:
    """Source bytes of ``modules`` and every project module they import, transitively."""
    seen: dict[str, bytes] = {}
    pending = list(modules)
    while pending:
        module = pending.pop()
        if module in seen:
            continue
        path = module_file(module)
        if path is None:
            raise ValueError(f"{module!r} is not a module of {PROJECT_PACKAGES}")
        seen[module] = path.read_bytes()
        is_package = path.name == "__init__.py"
        pending.extend(_imported(module, seen[module].decode(), is_package))
        if is_package:
            seen.update(_package_data(module, path.parent))
    return seen


def _package_data(package: str, folder: Path) -> dict[str, bytes]:
    """Files in a package's data folders (folders without ``__init__.py``, e.g. the report's
    ``templates/``), keyed ``package/relative/path``."""
    data = {}
    for sub in folder.iterdir():
        if sub.is_dir() and sub.name != "__pycache__" and not (sub / "__init__.py").exists():
            for file in sorted(p for p in sub.rglob("*") if p.is_file()):
                if "__pycache__" not in file.parts:
                    data[f"{package}/{file.relative_to(folder).as_posix()}"] = file.read_bytes()
    return data


@cache
def code_key(*modules: str) -> str:
    """SHA-256 (hex, 16 digits) over the sources of ``modules`` and every project module they
    import, transitively, plus ``library_versions()``."""
    sources = _sources(modules)
    digest = hashlib.sha256(repr(library_versions()).encode())
    for module in sorted(sources):
        digest.update(f"\x00{module}\x00".encode() + sources[module])
    return digest.hexdigest()[:16]


def modules_of(*modules: str) -> list[str]:
    """The project modules ``code_key(*modules)`` covers, sorted."""
    return sorted(_sources(modules))
