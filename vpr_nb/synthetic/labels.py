"""Content labels: what each rendered pixel shows, as one integer per pixel (``make_dataset(..., labels=True)``).

The renderer (:mod:`~vpr_nb.synthetic.render`) knows which stage drew a pixel, so it can say what the pixel
shows without changing a single pixel value. Label ``i`` is ``LABEL_NAMES[i]``:

- ``object``: the scene's static content: facades, trees, houses, poles, fences, roadside objects (what
  identifies the place);
- ``ground``: the ground plane (road, pavement, grass, track);
- ``skyline``: the far skyline ring (almost no parallax);
- ``sky``: the sky;
- ``occluder``: an image-space occluder box (queries only, ``occluder_rate``);
- ``distractor``: a parked car or pedestrian in 3-D that differs between visits (``distractor_rate``,
  :mod:`~vpr_nb.synthetic.distractors`).

The label of a pixel is the content drawn on top: sensor noise and rain streaks do not change it.
"""
from __future__ import annotations

LABEL_NAMES = ("object", "ground", "skyline", "sky", "occluder", "distractor")
OBJECT_LABEL, GROUND_LABEL, SKYLINE_LABEL, SKY_LABEL, OCCLUDER_LABEL, DISTRACTOR_LABEL = range(len(LABEL_NAMES))
