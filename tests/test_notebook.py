"""The notebooks' setup helper (vpr_nb.notebook)."""
import json
import random

import numpy as np
import pytest
import torch

from vpr_nb import notebook
from vpr_nb.package_data import committed_results_dir


@pytest.fixture
def restore_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_setup_seeds_and_sets_one_thread(restore_threads):
    torch.set_num_threads(2)
    s = notebook.setup("ci", seed=3)
    assert torch.get_num_threads() == 1
    a = (random.random(), np.random.rand(), torch.rand(1).item())
    notebook.setup("reproduce", seed=3)
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == a
    assert (s.profile, s.seed) == ("ci", 3)
    assert s.results_dir == committed_results_dir() and (s.results_dir / "04_netvlad.json").is_file()


@pytest.mark.parametrize("profile", ["CI", "full", None])
def test_unknown_profile_is_refused(profile, restore_threads):
    with pytest.raises(ValueError, match="PROFILE must be 'ci' or 'reproduce'"):
        notebook.setup(profile)
    with pytest.raises(ValueError, match="PROFILE must be 'ci' or 'reproduce'"):
        notebook.budget(profile, ci={}, reproduce={})


def test_budget_picks_the_profile_and_copies():
    ci, rep = {"epochs": 1, "seeds": [0]}, {"epochs": 8, "seeds": [0, 1, 2]}
    got = notebook.budget("ci", ci=ci, reproduce=rep)
    assert got == ci and notebook.budget("reproduce", ci=ci, reproduce=rep) == rep
    got["seeds"].append(5)
    assert ci["seeds"] == [0]           # a copy: the declaration is never edited through the budget


def test_budget_needs_the_same_keys():
    with pytest.raises(ValueError, match=r"only in ci: \['ablations'\], only in reproduce: \[\]"):
        notebook.budget("reproduce", ci={"epochs": 1, "ablations": False}, reproduce={"epochs": 8})
    with pytest.raises(ValueError, match="must be dicts"):
        notebook.budget("ci", ci=[1], reproduce={})


def test_committed_experiment_reads_the_config(tmp_path):
    config = {"epochs": 8, "seeds": [0, 1]}
    (tmp_path / "04_x.json").write_text(json.dumps({"notebook": "04_x", "config": config, "results": {}}))
    assert notebook.committed_experiment("04_x", results_dir=tmp_path) == config
    with pytest.raises(FileNotFoundError, match="notebooks/results/05_y.json"):
        notebook.committed_experiment("05_y", results_dir=tmp_path)
    (tmp_path / "06_z.json").write_text(json.dumps({"results": {}}))
    with pytest.raises(ValueError, match="no experiment config"):
        notebook.committed_experiment("06_z", results_dir=tmp_path)
    with pytest.raises(ValueError, match="stem"):
        notebook.committed_experiment("../04_x", results_dir=tmp_path)


def test_notebook_05_follows_the_course_recipe_on_notebook_04s_world():
    """05's committed results were computed with the course recipe as it is now (so the CI profile shows
    what the recipe gives) and on the world of notebook 04, whose rows it is read beside."""
    import json

    from vpr_nb.recipe import RECIPE, VALIDATION_WORLD

    nb04 = notebook.committed_experiment("04_netvlad")
    nb05 = notebook.committed_experiment("05_salad")
    assert nb05["recipe"] == json.loads(json.dumps(RECIPE.to_dict()))
    assert all(nb05["world"][k] == nb04["world"][k] for k in ("preset", "seed", "size"))
    assert nb05["worlds"]["validation"] == json.loads(json.dumps(VALIDATION_WORLD))
