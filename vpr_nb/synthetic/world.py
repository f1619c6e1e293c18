"""Generating a world: :func:`make_dataset` = a kind's layout and cameras, rendered split by split."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .._checks import check_int
from .cameras import query_draws
from .config import SPLITS, make_config
from .dataset import VPRDataset
from .distractors import place_distractors
from .kinds import WORLD_KINDS
from .render import render_all

RENDER_SEED_OFFSET = 7919   # a split's render seeds come from SeedSequence(seed + 7919), two per split


def make_dataset(preset: str = "city", seed: int = 0, size: str = "tiny",
                 splits: Sequence[str] = SPLITS, labels: bool = False, **overrides) -> VPRDataset:
    """Generate (deterministically from ``seed``) a synthetic VPR dataset.

    ``preset`` is a world kind (``"city"`` or ``"route"``, :data:`~vpr_nb.synthetic.kinds.WORLD_KINDS`);
    ``size`` is ``"tiny"`` (notebooks, CI) or ``"small"``; ``splits`` restricts rendering to some splits
    (geometry and the other splits' positions are still generated, so a split is identical whatever
    else is rendered); ``labels=True`` also renders each image's content labels (``db_labels``,
    ``q_labels``: uint8 (N, H, W), :data:`~vpr_nb.synthetic.labels.LABEL_NAMES`; the images are the same
    either way); ``overrides`` set any :class:`~vpr_nb.synthetic.config.WorldConfig` field
    (e.g. ``condition_strength=0.5``, ``distractor_rate=1.0``).
    """
    seed = check_int(seed, "seed", minimum=0)
    if not isinstance(labels, bool):
        raise ValueError(f"labels must be True or False, got {labels!r}")
    cfg = make_config(preset, size, **overrides)
    splits = tuple(splits)
    bad = [s for s in splits if s not in SPLITS]
    if bad or not splits:
        raise ValueError(f"splits must be a non-empty subset of {SPLITS}, got {splits}")
    kind = WORLD_KINDS[cfg.preset]
    # four streams: scene, cameras, (one unused: rendering draws from the per-split streams), query draws
    geo_rng, cam_rng, _, cond_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4))
    scene = kind.layout(cfg, geo_rng)
    cams = kind.cameras(cfg, cam_rng, scene)
    q_cond_idx, q_pitch, q_occ = query_draws(cfg, len(cams.q_pos), cond_rng)
    names = (cfg.db_condition, *[c for c in cfg.query_conditions if c != cfg.db_condition])
    q_cond_names = [cfg.query_conditions[i] for i in q_cond_idx]
    wanted = [SPLITS.index(s) for s in splits]
    dm, qm = np.isin(cams.db_split, wanted), np.isin(cams.q_split, wanted)
    # per-split render seeds so that a split's pixels do not depend on which other splits are rendered
    split_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed + RENDER_SEED_OFFSET).spawn(6)]
    # distractors (off by default): one visit per database place and per query, each from its own stream
    db_dis = q_dis = None
    if cfg.distractor_rate > 0:
        db_dis = place_distractors(cfg, scene, cams.db_pos, cams.db_place, seed, side=0)
        q_dis = place_distractors(cfg, scene, cams.q_pos, np.arange(len(cams.q_pos)), seed, side=1)
    db_img = np.zeros((dm.sum(), *cfg.image_size, 3), np.uint8)
    q_img = np.zeros((qm.sum(), *cfg.image_size, 3), np.uint8)
    db_lab = np.zeros((dm.sum(), *cfg.image_size), np.uint8) if labels else None
    q_lab = np.zeros((qm.sum(), *cfg.image_size), np.uint8) if labels else None
    db_sel, q_sel = np.flatnonzero(dm), np.flatnonzero(qm)
    for k in wanted:
        di = np.flatnonzero(cams.db_split[db_sel] == k)
        qi = np.flatnonzero(cams.q_split[q_sel] == k)
        if len(di):
            g = db_sel[di]
            db_img[di], lab = render_all(scene, cfg, cams.db_pos[g], cams.db_heading[g], np.zeros(len(g)),
                                         [cfg.db_condition] * len(g), np.zeros(len(g), int), split_rngs[2 * k],
                                         distractors=None if db_dis is None else db_dis.take(g), labels=True)
            if labels:
                db_lab[di] = lab
        if len(qi):
            g = q_sel[qi]
            q_img[qi], lab = render_all(scene, cfg, cams.q_pos[g], cams.q_heading[g], q_pitch[g],
                                        [q_cond_names[i] for i in g], q_occ[g], split_rngs[2 * k + 1],
                                        distractors=None if q_dis is None else q_dis.take(g), labels=True)
            if labels:
                q_lab[qi] = lab
    q_cond = np.array([names.index(c) for c in q_cond_names], dtype=np.int64)
    return VPRDataset(
        name=f"{preset}-{size}", config=cfg, seed=seed,
        db_images=db_img, q_images=q_img, db_utm=cams.db_pos[dm], q_utm=cams.q_tag[qm],
        db_heading=cams.db_heading[dm], q_heading=cams.q_heading[qm],
        db_condition=np.zeros(dm.sum(), np.int64), q_condition=q_cond[qm],
        db_split=cams.db_split[dm], q_split=cams.q_split[qm], db_place=cams.db_place[dm], q_place=cams.q_place[qm],
        condition_names=names, pos_radius=cfg.pos_radius, train_pos_radius=cfg.train_pos_radius,
        extra=dict(rendered_splits=splits, scene=scene), db_labels=db_lab, q_labels=q_lab,
    )
