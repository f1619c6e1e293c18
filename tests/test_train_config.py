"""How a TrainConfig is made: the one learning-rate default (vpr_nb.training.config.DEFAULT_LR) and the recipe's
TrainConfig, derived from the recipe by the fields the two share by name (Recipe.train_config)."""
import dataclasses

import pytest

from vpr_nb import config as C
from vpr_nb.recipe import RECIPE, Recipe
from vpr_nb.recipe.protocol import RUN_TRAINING, TRAINCONFIG_DEFAULTS
from vpr_nb.training import TrainConfig
from vpr_nb.training.config import DEFAULT_LR, train_config_from

SGD_RECIPE = dataclasses.replace(RECIPE, optimizer="sgd", patience=4, initial_candidate=False)


def _default(cls, name):
    return next(f.default for f in dataclasses.fields(cls) if f.name == name)


def test_one_learning_rate_default():
    assert DEFAULT_LR == 1e-3
    assert _default(TrainConfig, "lr") is DEFAULT_LR and _default(Recipe, "lr") is DEFAULT_LR   # the constant itself
    assert C.SECTIONS["train"] is TrainConfig and C.SECTIONS["train"]().lr is DEFAULT_LR      # the run config's
    assert TrainConfig().lr == RECIPE.lr == C.resolve("synthetic-route-ms").train.lr == 1e-3


def test_every_preset_keeps_its_learning_rate():
    lrs = {name: C.resolve(name).train.lr for name in C.PRESETS}
    assert lrs == {"synthetic-city-triplet": 0.05, "synthetic-city-dw": 0.05, "synthetic-city-netvlad": 0.05,
                   "synthetic-route-ms": 1e-3, "dwt-pitts30k": 1e-4, "salad-gsv": 6e-5,
                   "salad-cliquemining-msls": 6e-5}
    assert all(C.resolve(name).train.optimizer == "sgd" for name in lrs if name.startswith("synthetic-city"))


def test_every_trainconfig_field_is_the_recipes_by_name_or_set_on_purpose():
    train_fields = [f.name for f in dataclasses.fields(TrainConfig)]
    recipe_fields = {f.name for f in dataclasses.fields(Recipe)}
    per_run = {"epochs", "lr", "seed"}            # epochs = max_epochs; lr and seed are the run's arguments
    on_purpose = per_run | set(RUN_TRAINING) | set(TRAINCONFIG_DEFAULTS)
    by_name = [n for n in train_fields if n in recipe_fields and n not in on_purpose]
    assert by_name == ["optimizer", "weight_decay", "step_size", "gamma", "ns", "initial_candidate", "patience"]
    left = [n for n in train_fields if n not in by_name and n not in on_purpose]
    assert not left, (f"TrainConfig fields {left} are neither the recipe's by name nor set on purpose: add them to "
                      "Recipe, or to RUN_TRAINING / TRAINCONFIG_DEFAULTS in vpr_nb/recipe/protocol.py")
    assert not set(TRAINCONFIG_DEFAULTS) & recipe_fields and not set(RUN_TRAINING) & recipe_fields
    assert not set(TRAINCONFIG_DEFAULTS) & set(RUN_TRAINING) and set(RUN_TRAINING) == {"restore_best", "device"}
    # each source is honoured: a recipe whose shared fields all differ from the defaults passes every one on
    other = dataclasses.replace(RECIPE, optimizer="adamw", weight_decay=0.25, step_size=3, gamma=0.7, ns=(2, 4),
                                initial_candidate=False, patience=9, max_epochs=7, lr=5.0)
    cfg = other.train_config(0.125, 11)
    assert all(getattr(cfg, n) == getattr(other, n) for n in by_name)
    assert (cfg.epochs, cfg.lr, cfg.seed) == (7, 0.125, 11)
    assert all(getattr(cfg, k) == v for k, v in RUN_TRAINING.items())
    assert all(getattr(cfg, n) == getattr(TrainConfig(), n) for n in TRAINCONFIG_DEFAULTS)


def test_the_recipes_trainconfig_is_the_one_it_always_was():
    """Written out field by field: equal to the hand-copied TrainConfig that Recipe.train_config built before."""
    common = dict(momentum=0.9, weight_decay=1e-3, scheduler="step", step_size=5, gamma=0.5, linear_end_factor=0.2,
                  linear_steps=4000, ns=(1, 5, 10), restore_best=True, device="cpu", amp=False)
    assert RECIPE.train_config(3e-4, seed=2) == TrainConfig(epochs=24, optimizer="adam", lr=3e-4, seed=2,
                                                            initial_candidate=True, patience=6, **common)
    assert SGD_RECIPE.train_config(1e-3, 0) == TrainConfig(epochs=24, optimizer="sgd", lr=1e-3, seed=0,
                                                           initial_candidate=False, patience=4, **common)


def test_train_config_from_takes_fields_by_name_and_refuses_bad_input():
    run = C.resolve("synthetic-city-triplet")
    assert train_config_from(run.train) == run.train                  # a run config's train section is one
    assert train_config_from(RECIPE, epochs=3).epochs == 3 and train_config_from(RECIPE).epochs == 10
    with pytest.raises(ValueError, match="dataclass instance"):
        train_config_from({"lr": 0.1})
    with pytest.raises(ValueError, match="dataclass instance"):
        train_config_from(Recipe)
    with pytest.raises(ValueError, match=r"unknown TrainConfig field\(s\) \['max_epochs'\]; known fields: epochs"):
        train_config_from(RECIPE, max_epochs=3)
    with pytest.raises(ValueError, match="lr must be positive"):
        RECIPE.train_config(0.0, 0)
    with pytest.raises(ValueError, match="seed must be >= 0"):
        RECIPE.train_config(1e-3, -1)
    with pytest.raises(ValueError, match="seed must be an integer"):
        RECIPE.train_config(1e-3, 0.5)
