"""Interactive views for the notebooks: a pure function computes, a thin ipywidgets layer shows.

- :func:`distance_weight_curve` — the DW-T-Loss weight of Eq. (4), ``w = (1 + eps) / (d / sigma + eps) - 1``,
  on a grid of query-positive distances, plus the weights at a few marked distances and the relative
  spread of the weight over the positive range (the pure, tested part).
- :func:`distance_weight_explorer` — sliders for sigma and eps that redraw that curve (needs ipywidgets;
  the JupyterLab extension ``jupyterlab_widgets`` renders it).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._checks import check_int, check_positive
from .losses import distance_weight

__all__ = ["WeightCurve", "distance_weight_curve", "distance_weight_explorer"]


@dataclass(frozen=True)
class WeightCurve:
    """Output of :func:`distance_weight_curve`.

    Attributes:
        distances: ``(num,)`` query-positive distances in metres, from 0 to ``max_distance``.
        weights: ``(num,)`` Eq. (4) weights at ``distances``.
        marks: ``{distance: weight}`` at the requested marked distances.
        relative_spread: ``(w(0) - w(r)) / w(0)`` where ``r`` is the largest marked distance:
            how much the weight of the closest positive exceeds the farthest one's, relative to it.
    """

    distances: np.ndarray
    weights: np.ndarray
    marks: dict
    relative_spread: float


def distance_weight_curve(sigma: float = 800.0, eps: float = 0.1, max_distance: float = 1000.0, num: int = 201,
                          marks: Sequence[float] = (0.0, 5.0, 10.0, 25.0)) -> WeightCurve:
    """Eq. (4) of DW-T-Loss on a grid of distances, with the weights at ``marks`` (metres).

    ``relative_spread`` compares the weight at 0 m with the one at ``max(marks)`` (e.g. the 25 m
    evaluation radius): with ``sigma = 800`` m and ``eps = 0.1`` the weight is 10 at 0 m, 8.78 at
    10 m and 7.38 at 25 m (spread 0.26; 0.12 over the 10 m training radius), so the weight mostly
    rescales the loss by about 9 and only modulates it mildly with distance.
    """
    sigma = check_positive(sigma, "sigma")
    eps = check_positive(eps, "eps")
    max_distance = check_positive(max_distance, "max_distance")
    num = check_int(num, "num", minimum=2)
    try:
        mark_arr = np.asarray(list(marks), dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"marks must be a sequence of distances in metres, got {marks!r}") from None
    if mark_arr.ndim != 1 or mark_arr.size == 0:
        raise ValueError("marks must list at least one distance in metres, e.g. (0, 5, 10, 25)")
    if not np.isfinite(mark_arr).all() or (mark_arr < 0).any():
        raise ValueError(f"marks must be finite distances >= 0 m, got {mark_arr.tolist()}")
    distances = np.linspace(0.0, max_distance, num)
    weights = distance_weight(distances, sigma, eps)
    mark_w = distance_weight(mark_arr, sigma, eps)
    w0 = float(distance_weight(0.0, sigma, eps))
    w_far = float(distance_weight(float(mark_arr.max()), sigma, eps))
    return WeightCurve(distances=distances, weights=np.asarray(weights, dtype=np.float64),
                       marks={float(d): float(w) for d, w in zip(mark_arr, mark_w)},
                       relative_spread=(w0 - w_far) / w0)


def distance_weight_explorer(sigma: float = 800.0, eps: float = 0.1, max_distance: float = 1000.0,
                             marks: Sequence[float] = (0.0, 5.0, 10.0, 25.0)):
    """Sliders for sigma (log scale, 5 m to 5 km) and eps that redraw Eq. (4) (a thin ipywidgets view).

    Returns the ``ipywidgets.interactive`` object (display it as a cell's last expression). All numbers
    come from :func:`distance_weight_curve`.
    """
    sigma = check_positive(sigma, "sigma")
    eps = check_positive(eps, "eps")
    distance_weight_curve(sigma, eps, max_distance, 2, marks)  # validate before building widgets
    try:
        import ipywidgets as widgets
    except ImportError:  # pragma: no cover - ipywidgets is pinned in environment.txt
        raise ValueError("the explorer needs ipywidgets (pinned in environment.txt); "
                         "use distance_weight_curve() for the numbers") from None
    import matplotlib.pyplot as plt

    def show(sigma: float, eps: float) -> None:
        curve = distance_weight_curve(sigma, eps, max_distance, 401, marks)
        fig, ax = plt.subplots(figsize=(6, 3))
        ax.plot(curve.distances, curve.weights)
        ax.axhline(0.0, color="0.6", lw=1)
        ax.axvspan(0, max(curve.marks), color="tab:green", alpha=0.15, label="positive range")
        ax.set(xlabel="query-positive distance (m)", ylabel="weight w, Eq. (4)",
               title=f"sigma = {sigma:g} m, eps = {eps:g}")
        ax.legend(loc="upper right")
        plt.show()
        print("w at " + ", ".join(f"{d:g} m: {w:.3f}" for d, w in curve.marks.items())
              + f" | relative spread over the positive range: {curve.relative_spread:.3f}")

    sigma_slider = widgets.FloatLogSlider(value=sigma, base=10, min=np.log10(5.0), max=np.log10(5000.0),
                                          step=0.05, description="sigma (m)", continuous_update=False)
    eps_slider = widgets.FloatLogSlider(value=eps, base=10, min=-3, max=1, step=0.05,
                                        description="eps", continuous_update=False)
    return widgets.interactive(show, sigma=sigma_slider, eps=eps_slider)
