"""The package code a task runs (vpr_nb.code_digest): its import graph equals grimp's, its digest follows the
modules a task imports and not the others."""
import pytest

from vpr_nb import code_digest as cd
from vpr_nb.losses import DWTripletLoss
from vpr_nb.onoff import dwt
from vpr_nb.recipe import Method
from vpr_nb.recipe.task import code_modules


def test_the_import_graph_equals_grimps():
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("vpr_nb")
    mine = cd.import_graph()
    assert set(mine) == set(graph.modules)
    assert {m: set(v) for m, v in mine.items()} == {m: graph.find_modules_directly_imported_by(m) for m in mine}


def _package(root):
    pkg = root / "vpr_nb"
    (pkg / "samplers").mkdir(parents=True)
    (pkg / "weights").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "samplers" / "__init__.py").write_text("")
    (pkg / "samplers" / "clique.py").write_text("X = 1\n")
    (pkg / "task.py").write_text("def run():\n    from .samplers import clique\n    return clique.X\n")
    (pkg / "report.py").write_text("from .task import run\n")
    (pkg / "weights" / "w.bin").write_bytes(b"\0")
    (root / "notebooks").mkdir()
    (root / "notebooks" / "07_clique_mining.py").write_text("# text\n")
    return pkg


def test_the_digest_follows_the_code_a_task_imports_and_nothing_else(tmp_path):
    pkg = _package(tmp_path)
    assert cd.closure(["vpr_nb.task"], pkg) == {"vpr_nb", "vpr_nb.task", "vpr_nb.samplers", "vpr_nb.samplers.clique"}
    before = cd.code_digest(["vpr_nb.task"], pkg)
    (tmp_path / "notebooks" / "07_clique_mining.py").write_text("# other text\n")
    (pkg / "report.py").write_text("from .task import run  # a module that imports the task, not one it runs\n")
    assert cd.code_digest(["vpr_nb.task"], pkg) == before
    (pkg / "task.py").write_text('def run():\n    """Run it."""\n    from .samplers import clique  # lazily\n\n'
                                 '    return (clique.X)\n')
    assert cd.code_digest(["vpr_nb.task"], pkg) == before            # a docstring, a comment, a reflowed line
    (pkg / "samplers" / "clique.py").write_text("X = 2\n")        # a module the task imports (lazily)
    changed = cd.code_digest(["vpr_nb.task"], pkg)
    assert changed != before
    (pkg / "weights" / "w.bin").write_bytes(b"\1")                 # the shipped weights
    assert cd.code_digest(["vpr_nb.task"], pkg) != changed
    with pytest.raises(ValueError, match="not modules of the package"):
        cd.closure(["vpr_nb.nowhere"], pkg)


def test_a_task_runs_the_modules_of_its_objects_and_not_the_reports():
    grid = code_modules(Method("DW-T", "netvlad", DWTripletLoss(sigma=18.0, eps=0.1)))
    assert {"vpr_nb.recipe.task", "vpr_nb.losses.triplet"} <= grid
    runs = cd.closure(code_modules(*dwt.methods("on")))
    assert "vpr_nb.training.triplet_source" in runs and "vpr_nb.samplers.clique" in runs
    assert not runs & {"vpr_nb.report", "vpr_nb.remake", "vpr_nb.verdict", "vpr_nb.onoff.dwt", "vpr_nb.plots",
                       "vpr_nb.grading"}
