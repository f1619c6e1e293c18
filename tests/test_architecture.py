"""The package's shape: six layers with imports only downward, no circle, short modules of one job.

The layers and contracts are in ``pyproject.toml`` (``[tool.importlinter]``) and ``vpr_nb/__init__.py`` says
what belongs in each; README's test command runs ``lint-imports`` on the package. These tests check that the
contracts bite (a copy of the package with one wrong import fails them) and the rules import-linter does not
know: module length and imports hidden in function bodies."""
from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "vpr_nb"
MAX_LINES = 500
LINT_IMPORTS = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")


def _modules():
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def _lint_copy(tmp_path: Path, edits: dict[str, str]) -> subprocess.CompletedProcess:
    """``lint-imports`` on a copy of the package with ``edits`` ({module path: line appended}) applied."""
    shutil.copytree(PACKAGE, tmp_path / "vpr_nb", ignore=shutil.ignore_patterns("__pycache__", "*.pt"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    for rel, line in edits.items():
        with open(tmp_path / rel, "a", encoding="utf-8") as f:
            f.write("\n" + line + "\n")
    return subprocess.run([LINT_IMPORTS, "--no-cache"], cwd=tmp_path, capture_output=True, text=True,
                          env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(tmp_path)}, timeout=300)


needs_linter = pytest.mark.skipif(LINT_IMPORTS is None, reason="import-linter is not installed (requirements-dev.txt)")


@needs_linter
def test_the_package_keeps_its_contracts(tmp_path):
    out = _lint_copy(tmp_path, {})
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 broken" in out.stdout


@needs_linter
@pytest.mark.parametrize("edits, broken", [
    # a basics module reaching up to a front door
    ({"vpr_nb/_checks.py": "from . import report  # noqa"}, "layers"),
    # a method reaching up to the training loop
    ({"vpr_nb/evaluation.py": "from . import training  # noqa"}, "layers"),
    # two data modules importing each other
    ({"vpr_nb/image_tensors.py": "from . import split  # noqa",
      "vpr_nb/split.py": "from . import image_tensors  # noqa"}, "no import circle"),
    # one dataset format reading another's module
    ({"vpr_nb/datasets/pitts.py": "from . import msls  # noqa"}, "dataset formats"),
    # a module no layer names
    ({"vpr_nb/stray.py": "x = 1"}, "layers"),
])
def test_a_wrong_import_breaks_a_contract(tmp_path, edits, broken):
    out = _lint_copy(tmp_path, edits)
    assert out.returncode != 0, out.stdout
    broken_lines = [line for line in out.stdout.splitlines() if line.endswith("BROKEN")]
    assert any(line.startswith(broken) for line in broken_lines), out.stdout


def test_every_module_is_short():
    long = {str(p.relative_to(ROOT)): n for p in _modules() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them by idea): {long}"


def test_every_module_says_its_job():
    missing = [str(p.relative_to(ROOT)) for p in _modules()
               if p.read_text().strip() and not ast.get_docstring(ast.parse(p.read_text()))]
    assert not missing, f"modules without a docstring stating their job: {missing}"


def _function_level_package_imports(path: Path):
    """(line number, source line) of each ``from .x import y`` / ``import vpr_nb...`` inside a function."""
    source = path.read_text()
    lines = source.splitlines()
    found = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            package = ((isinstance(child, ast.ImportFrom) and (child.level > 0 or (child.module or "").startswith("vpr_nb")))
                       or (isinstance(child, ast.Import) and any(a.name.startswith("vpr_nb") for a in child.names)))
            if in_function and package:
                found.append((child.lineno, " ".join(lines[child.lineno - 1:child.end_lineno])))
            visit(child, inner)

    visit(ast.parse(source), False)
    return found


# the reasons a package import may sit in a function, said in its line's comment: it loads a heavy optional
# library (matplotlib's pyplot), or the grader's sandboxed runner must not import numpy before dropping root
ALLOWED_REASONS = ("# optional library:", "# sandbox:")


def test_no_package_import_hides_in_a_function():
    """A function-level import of the package's own modules hides a dependency (often a circle); the only
    ones allowed have one of :data:`ALLOWED_REASONS` in their comment."""
    hidden = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in _modules()
              for n, line in _function_level_package_imports(p) if not any(r in line for r in ALLOWED_REASONS)]
    assert not hidden, "imports inside functions (move them to the module's top):\n" + "\n".join(hidden)


def test_the_hidden_import_rule_sees_one(tmp_path):
    bad = tmp_path / "m.py"
    bad.write_text('"""x"""\ndef f():\n    from .losses import triplet_loss\n    return triplet_loss\n')
    assert [n for n, _ in _function_level_package_imports(bad)] == [3]


def test_importing_the_package_or_its_kernels_starts_no_numerical_library():
    """vpr_nb.kernels pins the CPU kernels before torch, numpy and faiss start, so importing it (and the
    package) must not start them."""
    code = ("import sys, vpr_nb, vpr_nb.kernels, vpr_nb.errors, vpr_nb.seeding; "
            "print(sorted(m for m in ('torch', 'numpy', 'faiss', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
