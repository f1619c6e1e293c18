"""Tests for :mod:`vpr_nb.widgets`: the pure Eq. (4) curve (hand-computed values) and its thin view."""
from __future__ import annotations

import numpy as np
import pytest

from vpr_nb.losses import distance_weight
from vpr_nb.widgets import distance_weight_curve, distance_weight_explorer


def test_curve_hand_values():
    # Eq. (4): w = (1 + eps) / (d / sigma + eps) - 1 with sigma = 800, eps = 0.1
    c = distance_weight_curve(800.0, 0.1, max_distance=1600.0, num=3, marks=(0.0, 10.0, 25.0))
    assert np.allclose(c.distances, [0.0, 800.0, 1600.0])
    assert np.allclose(c.weights, [10.0, 0.0, 1.1 / 2.1 - 1.0])      # w(sigma) = 0, negative beyond
    assert c.marks[0.0] == pytest.approx(10.0)                       # 1 / eps at 0 m
    assert c.marks[10.0] == pytest.approx(1.1 / 0.1125 - 1.0)        # 8.777...
    assert c.marks[25.0] == pytest.approx(1.1 / 0.13125 - 1.0)       # 7.380...
    assert c.relative_spread == pytest.approx((10.0 - (1.1 / 0.13125 - 1.0)) / 10.0)


def test_curve_matches_losses_and_is_decreasing():
    c = distance_weight_curve(50.0, 0.5, max_distance=300.0, num=61)
    assert np.allclose(c.weights, distance_weight(c.distances, 50.0, 0.5))
    assert (np.diff(c.weights) < 0).all()


def test_small_sigma_spreads_the_weight():
    assert distance_weight_curve(800.0).relative_spread < distance_weight_curve(25.0).relative_spread


@pytest.mark.parametrize("kwargs, match", [
    ({"sigma": 0.0}, "sigma"), ({"eps": -1.0}, "eps"), ({"max_distance": 0.0}, "max_distance"),
    ({"num": 1}, "num"), ({"marks": ()}, "marks"), ({"marks": (-1.0,)}, "marks"),
    ({"marks": (float("nan"),)}, "marks"), ({"marks": "abc"}, "marks"),
])
def test_curve_rejects_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        distance_weight_curve(**kwargs)


def test_explorer_builds_two_sliders():
    w = distance_weight_explorer(800.0, 0.1)
    names = sorted(child.description for child in w.children[:2])
    assert names == ["eps", "sigma (m)"]
    with pytest.raises(ValueError, match="sigma"):
        distance_weight_explorer(sigma=-5.0)
