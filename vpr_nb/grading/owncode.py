"""The "own code" rule: an answer computes its result itself, without the course library.

Two forms of one rule:

* :func:`source_violations` (the grader's, and the one that counts): static analysis of the submitted
  source, in the trusted grader process, before anything runs. It parses the solution cells (IPython
  magics turned into calls first) and refuses imports outside a short list of numeric modules, the
  library (``vpr_nb``) by any name the setup cells bound to it, names an exercise forbids (such as
  ``TripletMarginLoss``), the built-ins that reach code or files indirectly (``__import__``, ``exec``,
  ``eval``, ``getattr``, ``open``, ``globals``, ``get_ipython`` ...), numpy's and torch's own file access
  (:data:`FILE_ACCESS`: ``np.fromfile``, ``.tofile``, ``np.savetxt``, ``np.load``, ``torch.save`` ...,
  as an attribute or imported by name), dunder attributes that walk object internals (``__globals__``,
  ``__subclasses__`` ...) and strings naming the library. What it cannot see it cannot be fooled by: the
  student's process never decides whether the rule holds.
* :func:`library_references` / :func:`assert_own_code` (for a kernel: the student's own check, and
  nbgrader's autograde, which runs the test cells in the student's kernel): follows the live function's
  code objects, globals, closures and defaults.
"""
from __future__ import annotations

import ast
import functools
import inspect
import types

ALLOWED_IMPORTS = frozenset({
    "numpy", "torch", "math", "cmath", "itertools", "functools", "collections", "statistics", "operator",
    "heapq", "bisect", "typing", "dataclasses", "fractions", "decimal", "json", "re", "string", "random"})
FORBIDDEN_BUILTINS = frozenset({
    "__import__", "eval", "exec", "compile", "open", "globals", "locals", "vars", "getattr", "setattr",
    "delattr", "breakpoint", "input", "help", "exit", "quit", "memoryview", "get_ipython", "__builtins__",
    "__loader__", "__spec__", "__file__"})
FILE_ACCESS = frozenset({   # numpy's and torch's functions and methods that read or write files by name
    "fromfile", "tofile", "savetxt", "loadtxt", "genfromtxt", "fromregex", "memmap", "open_memmap", "save",
    "savez", "savez_compressed", "load", "dump", "from_file", "DataSource", "npyio", "serialization",
    "load_library", "ctypeslib", "open", "package"})
FORBIDDEN_ATTRIBUTES = frozenset({   # ways from numpy/torch to modules, files and frames
    "sys", "modules", "os", "builtins", "importlib", "import_module", "subprocess", "ctypes", "system", "popen",
    "hub", "f_globals", "f_locals", "f_back", "gi_frame", "tb_frame", "func_globals", "attrgetter",
    "methodcaller"}) | FILE_ACCESS
SAFE_DUNDERS = frozenset({
    "__init__", "__call__", "__len__", "__getitem__", "__setitem__", "__iter__", "__next__", "__repr__",
    "__str__", "__eq__", "__ne__", "__lt__", "__le__", "__gt__", "__ge__", "__hash__", "__add__", "__radd__",
    "__sub__", "__rsub__", "__mul__", "__rmul__", "__truediv__", "__rtruediv__", "__matmul__", "__neg__",
    "__contains__", "__enter__", "__exit__", "__name__", "__post_init__", "__bool__", "__float__", "__int__"})


def _python_source(source: str) -> str:
    """A cell's source as plain Python (IPython magics become ``get_ipython()`` calls, which the rule refuses)."""
    try:
        from IPython.core.inputtransformer2 import TransformerManager
    except ImportError:                     # no IPython: a magic line stays a syntax error
        return source
    return TransformerManager().transform_cell(source)


def library_names(sources, package: str = "vpr_nb") -> set[str]:
    """Names that ``sources`` (the instructor's setup cells) bind to ``package`` or to something of it."""
    names: set[str] = set()

    def rooted(node) -> bool:
        while isinstance(node, ast.Attribute):
            node = node.value
        return isinstance(node, ast.Name) and node.id in names

    for source in sources:
        try:
            tree = ast.parse(_python_source(source))
        except SyntaxError:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == package:
                names.update(a.asname or a.name for a in node.names)
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] == package:
                        names.add(a.asname or a.name.split(".")[0])
            elif isinstance(node, ast.Assign) and rooted(node.value):
                names.update(t.id for t in node.targets if isinstance(t, ast.Name))
    return names


def source_violations(sources, package: str = "vpr_nb", forbid_names=(), setup_sources=()) -> list[str]:
    """Every way the solution ``sources`` break the own-code rule ([] when they keep it).

    Args:
        sources: the solution cells' code, as submitted.
        package: the library the answer must not use.
        forbid_names: further names the exercise forbids (e.g. ``TripletMarginLoss``), as a name or an attribute.
        setup_sources: the instructor's cells that run before the solution; names they bind to ``package``
            are forbidden too.

    Raises:
        SyntaxError: a solution cell does not parse (the message names the line).
    """
    lib = library_names(setup_sources, package)
    forbid = set(forbid_names)
    found: list[str] = []
    for source in sources:
        tree = ast.parse(_python_source(source))
        for node in ast.walk(tree):
            line = getattr(node, "lineno", "?")
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] not in ALLOWED_IMPORTS:
                        found.append(f"imports {a.name} (line {line})")
            elif isinstance(node, ast.ImportFrom):
                mod = "." * node.level + (node.module or "")
                parts = set(mod.split("."))
                if node.level or mod.split(".")[0] not in ALLOWED_IMPORTS:
                    found.append(f"imports from {mod} (line {line})")
                elif parts & FORBIDDEN_ATTRIBUTES:
                    found.append(f"imports from {mod}{_file_note(parts)} (line {line})")
                found.extend(f"imports * from {mod} (name what you use) (line {line})" if a.name == "*" else
                             f"uses {a.name}{_file_note({a.name})} (line {line})" for a in node.names
                             if a.name in forbid or a.name in FORBIDDEN_ATTRIBUTES or a.name == "*")
            elif isinstance(node, ast.Name):
                if node.id == package or node.id in lib:
                    found.append(f"uses {node.id}, which is {package}'s (line {line})")
                elif node.id in forbid or node.id in FORBIDDEN_BUILTINS:
                    found.append(f"uses {node.id} (line {line})")
            elif isinstance(node, ast.Attribute):
                if node.attr in forbid or node.attr in FORBIDDEN_ATTRIBUTES:
                    found.append(f"uses .{node.attr}{_file_note({node.attr})} (line {line})")
                elif node.attr.startswith("__") and node.attr.endswith("__") and node.attr not in SAFE_DUNDERS:
                    found.append(f"reaches into .{node.attr} (line {line})")
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and package in node.value:
                found.append(f"names {package!r} in the string {node.value[:40]!r} (line {line})")
    return list(dict.fromkeys(found))


def _file_note(names) -> str:
    return ", which accesses files" if set(names) & FILE_ACCESS else ""


def own_code_message(name: str, found, package: str = "vpr_nb", forbid_names=()) -> str:
    """The feedback for an answer that breaks the rule."""
    banned = ", ".join((package,) + tuple(forbid_names))
    return (f"{name} must compute its result itself with plain Python, numpy or torch (not {banned}; imports "
            f"allowed: {', '.join(sorted(ALLOWED_IMPORTS))}), but your solution " + "; ".join(found))


def library_references(fn, package: str = "vpr_nb", forbid_names=()) -> list[str]:
    """How a function written in a notebook reaches ``package`` (or one of ``forbid_names``).

    Follows the function's code (nested functions and lambdas included), the globals it names, its
    closure and default arguments, and recursively every helper function or class defined in the
    notebook (module ``__main__``); reports each module, function, class or object of ``package`` it
    reaches, an ``import`` of it, a string naming it, and every name in ``forbid_names`` it uses.
    """
    if not callable(fn):
        raise ValueError(f"library_references needs a function, got {type(fn).__name__}")
    found, seen = [], set()

    def of_package(obj) -> str | None:
        mod = obj.__name__ if isinstance(obj, types.ModuleType) else getattr(obj, "__module__", None)
        if not isinstance(mod, str) and not isinstance(obj, (type, types.FunctionType)):
            mod = getattr(type(obj), "__module__", None)
        if isinstance(mod, str) and (mod == package or mod.startswith(package + ".")):
            return mod
        return None

    def visit_code(code, globs, owner):
        for name in code.co_names:
            if name == package or name.startswith(package + ".") or name in forbid_names:
                found.append(f"{owner} uses {name!r}")
            elif name in globs:
                visit_obj(globs[name], name, owner)
        for const in code.co_consts:
            if isinstance(const, types.CodeType):
                visit_code(const, globs, owner)
            elif isinstance(const, str) and package in const:
                found.append(f"{owner} names {package!r} in the string {const[:40]!r}")

    def visit_obj(obj, name, owner):
        if id(obj) in seen:
            return
        seen.add(id(obj))
        mod = of_package(obj)
        if mod is not None:
            found.append(f"{owner} uses {name} (from {mod})")
        elif isinstance(obj, types.FunctionType) and obj.__module__ == "__main__":
            visit_function(obj)
        elif isinstance(obj, functools.partial):
            visit_obj(obj.func, name, owner)
        elif isinstance(obj, type) and obj.__module__ == "__main__":
            for attr, value in vars(obj).items():
                visit_obj(value, f"{obj.__name__}.{attr}", obj.__name__)
            for base in obj.__mro__[1:]:
                visit_obj(base, base.__name__, obj.__name__)

    def visit_function(f):
        f = inspect.unwrap(f)
        if isinstance(f, (types.MethodType, staticmethod, classmethod)):
            f = f.__func__
        if not isinstance(f, types.FunctionType):
            return
        owner = f.__name__
        visit_code(f.__code__, f.__globals__, owner)
        for cell in f.__closure__ or ():
            try:
                visit_obj(cell.cell_contents, "a closure variable", owner)
            except ValueError:            # an empty cell
                pass
        for value in (f.__defaults__ or ()) + tuple((f.__kwdefaults__ or {}).values()):
            visit_obj(value, "a default argument", owner)

    seen.add(id(fn))
    if of_package(fn) is not None:
        return [f"{getattr(fn, '__name__', fn)!s} is {of_package(fn)}'s own"]
    visit_function(fn)
    return found


def assert_own_code(fn, package: str = "vpr_nb", forbid_names=()) -> None:
    """Hidden-test check: ``fn`` computes its answer itself, without calling into ``package``.

    Raises:
        AssertionError: naming what the answer uses, with the fix.
    """
    refs = library_references(fn, package, forbid_names)
    name = getattr(fn, "__name__", "the answer")
    assert not refs, (f"{name} must compute its result itself (plain Python, numpy or torch), but "
                      + "; ".join(dict.fromkeys(refs)) + f"; remove the use of {package}"
                      + (f" and of {', '.join(forbid_names)}" if forbid_names else ""))
