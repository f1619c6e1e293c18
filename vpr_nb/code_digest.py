"""The digest of the package code a computation runs: the modules it imports, followed statically, not the whole
package, so that a change to an unrelated module (a report, a plot, a grader) keeps a stored result valid.

:func:`import_graph` reads every module of a package folder with :mod:`ast` and lists the package modules each
one imports: at module level and inside functions (a lazy import runs too), absolute (``import vpr_nb.x``,
``from vpr_nb.x import y``) and relative (``from ..x import y``); ``from p import name`` counts ``p.name`` when
that is a module, else ``p``. :func:`closure` follows those edges from some modules and adds every parent
package (its ``__init__`` runs on import). :func:`code_digest` hashes that closure, each module by its syntax
tree without docstrings (a comment, a docstring or a reflowed line is not a change), and every data file of the
package (the shipped weights) by its bytes: path and content, in a fixed order.

What it cannot see: a program that reads its own docstrings (none that a task runs), code reached without an
import statement (``importlib.import_module`` with a computed name, ``__import__``; the package has none outside
its grader, which names them only to refuse them) and code outside the package. ``tests/test_code_digest.py``
checks the graph against grimp's (import-linter's).
"""
from __future__ import annotations

import ast
import hashlib
from functools import lru_cache
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
_SKIP_SUFFIXES = (".pyc", ".tmp")


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _source_files(root: Path) -> dict[str, Path]:
    return {_module_name(p, root): p for p in sorted(root.rglob("*.py")) if "__pycache__" not in p.parts}


def _imports(tree: ast.AST, name: str, is_package: bool, known: set[str]) -> set[str]:
    """The modules of ``known`` that the module ``name`` (parsed as ``tree``) imports."""
    package = name if is_package else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            subs = [f"{stem}.{a.name}" for a in node.names]      # ``from p import m`` of a module m: p.m
            targets = [t for t in subs if t in known]
            if len(targets) < len(subs):                          # of a name defined in p: p
                targets.append(stem)
        else:
            continue
        for t in targets:
            while t and t not in known:          # ``import vpr_nb.x.y`` of a name: its nearest module
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def import_graph(root=None) -> dict[str, frozenset[str]]:
    """Module name -> the package modules it imports (statically; see the module docstring). ``root``: a package
    folder (default: this installed package, read once per process)."""
    return _installed_graph() if root is None else _graph(Path(root).resolve())


@lru_cache(maxsize=1)
def _installed_graph() -> dict[str, frozenset[str]]:
    return _graph(PACKAGE_DIR)


def _graph(root: Path) -> dict[str, frozenset[str]]:
    files = _source_files(root)
    known = set(files)
    return {name: frozenset(_imports(ast.parse(path.read_bytes(), str(path)), name, path.name == "__init__.py",
                                     known))
            for name, path in files.items()}


def closure(modules, root=None) -> frozenset[str]:
    """``modules`` (names of package modules), everything they import, transitively, and their parent packages.
    A name that is not a module of the package is refused."""
    graph = import_graph(root)
    todo = list(modules)
    unknown = sorted(m for m in todo if m not in graph)
    if unknown:
        raise ValueError(f"not modules of the package at {root}: {unknown}")
    seen: set[str] = set()
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        todo.extend(graph[m])
        parent = m.rpartition(".")[0]
        if parent in graph:
            todo.append(parent)
    return frozenset(seen)


def _file_digest(path: Path) -> bytes:
    """A Python module by its syntax tree without docstrings (so a comment, a docstring or a reflowed line
    changes nothing), any other file by its bytes."""
    data = path.read_bytes()
    if path.suffix == ".py":
        tree = ast.parse(data, str(path))
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body \
                    and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
        data = ast.dump(tree, include_attributes=False).encode()
    return hashlib.sha256(data).digest()


@lru_cache(maxsize=None)
def _installed_file_digest(path: Path) -> bytes:
    return _file_digest(path)


def code_digest(modules, root=None) -> str:
    """SHA-256 over the source of :func:`closure` of ``modules`` and every non-Python file of the package (relative
    path and bytes; caches skipped). ``root``: a package folder (default: this installed package, whose files
    are read once per process: a kernel runs the code it imported until it restarts)."""
    names = closure(modules, root)
    installed = root is None
    root = PACKAGE_DIR if installed else Path(root).resolve()
    files = _source_files(root)
    data = [p for p in sorted(root.rglob("*")) if p.is_file() and p.suffix != ".py"
            and "__pycache__" not in p.parts and p.suffix not in _SKIP_SUFFIXES]
    h = hashlib.sha256()
    for path in sorted([files[n] for n in names] + data):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(_installed_file_digest(path) if installed else _file_digest(path))
    return h.hexdigest()
