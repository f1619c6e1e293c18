"""Tests of the synthetic world's content labels and distractors (vpr_nb.synthetic.labels, .distractors):
the images are unchanged by asking for labels and by the distractor knob at 0 (pinned hashes of the course's
tiny worlds), distractors appear in database and queries alike, differ between visits, and are 3-D."""
import hashlib

import numpy as np
import pytest

from vpr_nb.synthetic import LABEL_NAMES, make_config, make_dataset
from vpr_nb.synthetic.distractors import Distractors, place_distractors
from vpr_nb.synthetic.labels import DISTRACTOR_LABEL, OCCLUDER_LABEL, SKY_LABEL, SKYLINE_LABEL
from vpr_nb.synthetic.render import render_all

SMALL_CITY = dict(blocks=(3, 2), image_size=(24, 32))
SMALL_ROUTE = dict(num_frames=80, image_size=(24, 32))

# sha256 of db_images + q_images of make_dataset(preset, 0, size="tiny"), all splits, recorded before labels and
# distractors existed: asking for labels, and distractor_rate = 0 (the default), must leave every bit alone.
PINNED_TINY = {"city": "a64295e9a44537799d2cd15d2abb692d1798650ac2360dbc51d896173c31233e",
               "route": "44f21f1a14c93dfd9a02a69f63f2414b2d3effaaccb4e56ed56417434f3b96e6"}


def _digest(ds) -> str:
    return hashlib.sha256(np.ascontiguousarray(ds.db_images).tobytes()
                          + np.ascontiguousarray(ds.q_images).tobytes()).hexdigest()


@pytest.mark.parametrize("preset", ["city", "route"])
def test_tiny_worlds_are_pinned_with_labels_and_without_distractors(preset):
    ds = make_dataset(preset, 0, size="tiny", labels=True)
    assert _digest(ds) == PINNED_TINY[preset], f"the {preset} tiny world's pixels changed"
    for side in ("db", "q"):
        lab, img = getattr(ds, f"{side}_labels"), getattr(ds, f"{side}_images")
        assert lab.shape == img.shape[:3] and lab.dtype == np.uint8
        assert not (lab == DISTRACTOR_LABEL).any()                     # rate 0: no distractor anywhere
        assert (lab == SKY_LABEL).any() and (lab == SKYLINE_LABEL).any()
    assert not (ds.db_labels == OCCLUDER_LABEL).any()                  # occluders: queries only
    assert (ds.q_labels == OCCLUDER_LABEL).any() == (preset == "city")  # the route has none
    train = ds.train
    assert train.db_labels.shape[0] == len(train.db_images) and train.q_labels.shape[0] == len(train.q_images)


@pytest.fixture(scope="module")
def route_pair():
    """The small route with distractors, with and without labels."""
    return (make_dataset("route", 0, labels=True, distractor_rate=2.0, **SMALL_ROUTE),
            make_dataset("route", 0, distractor_rate=2.0, **SMALL_ROUTE))


def test_labels_leave_images_alone(route_pair):
    with_labels, without = route_pair
    assert without.db_labels is None and without.q_labels is None
    np.testing.assert_array_equal(with_labels.db_images, without.db_images)
    np.testing.assert_array_equal(with_labels.q_images, without.q_images)
    city = [make_dataset("city", 1, labels=flag, distractor_rate=1.0, **SMALL_CITY) for flag in (True, False)]
    assert _digest(city[0]) == _digest(city[1])
    assert sorted(np.unique(city[0].q_labels)) == list(range(len(LABEL_NAMES)))   # every label shows up


def test_distractors_in_database_and_queries_and_new_at_every_visit(route_pair):
    ds, _ = route_pair
    db_mask, q_mask = ds.db_labels == DISTRACTOR_LABEL, ds.q_labels == DISTRACTOR_LABEL
    assert db_mask.any(axis=(1, 2)).mean() > 0.3 and q_mask.any(axis=(1, 2)).mean() > 0.3
    # a route query stands at its database frame (+- 0.8 m): same place, another visit, other distractors
    both = db_mask.any(axis=(1, 2)) | q_mask.any(axis=(1, 2))
    same = [(db_mask[i] == q_mask[i]).all() for i in np.flatnonzero(both)]
    assert np.mean(same) < 0.2
    plain = make_dataset("route", 0, **SMALL_ROUTE)
    assert not np.array_equal(plain.db_images, ds.db_images) and not np.array_equal(plain.q_images, ds.q_images)


def test_distractor_placement_is_per_visit_and_deterministic():
    ds = make_dataset("city", 0, **SMALL_CITY, splits=("test",))
    cfg, scene = make_config("city", distractor_rate=2.0, **SMALL_CITY), ds.extra["scene"]
    cams = np.repeat(ds.db_utm[:3], 2, axis=0)                       # every position twice: two visits each
    a = place_distractors(cfg, scene, cams, np.arange(6), seed=0, side=1)
    b = place_distractors(cfg, scene, cams, np.arange(6), seed=0, side=1)
    np.testing.assert_array_equal(a.a, b.a)
    for v in range(0, 6, 2):
        first, second = a.a[a.face_visit == v], a.a[a.face_visit == v + 1]
        assert len(first) % 4 == 0 and not (len(first) == len(second) and np.allclose(first, second))
    db = place_distractors(cfg, scene, cams, np.arange(6), seed=0, side=0)
    assert not (len(db.a) == len(a.a) and np.allclose(db.a, a.a))   # the database's streams differ
    shared = place_distractors(cfg, scene, cams, np.zeros(6, int), seed=0, side=0)
    assert set(shared.face_visit.tolist()) <= {0}                    # one visit: one set of boxes for all cameras
    with pytest.raises(ValueError, match="non-negative"):
        place_distractors(cfg, scene, cams, -np.ones(6, int), seed=0, side=0)


def test_a_distractor_is_three_dimensional():
    # one car-sized box on a city street, seen from 14 m and from 7 m: nearer, it covers more pixels, lower down
    ds = make_dataset("city", 0, **SMALL_CITY, splits=("test",))
    cfg, scene = ds.config, ds.extra["scene"]
    pitch = cfg.block_size + cfg.street_width
    box = np.array([[2 * pitch + 20, -1.0], [2 * pitch + 24, -1.0], [2 * pitch + 24, 1.0], [2 * pitch + 20, 1.0]])
    dis = Distractors(a=box, b=np.roll(box, -1, 0), z1=np.full(4, 1.5), colour=np.full((4, 3), 0.8),
                      face_visit=np.zeros(4, int), camera_visit=np.zeros(2, int))
    pos = np.array([[2 * pitch + 6, 0.0], [2 * pitch + 13, 0.0]])
    imgs, lab = render_all(scene, cfg, pos, np.zeros(2), np.zeros(2), ["summer"] * 2, np.zeros(2, int),
                           np.random.default_rng(0), distractors=dis, labels=True)
    far, near = (lab == DISTRACTOR_LABEL).sum(axis=(1, 2))
    assert 0 < far < near
    rows = [np.flatnonzero((lab[i] == DISTRACTOR_LABEL).any(1)).max() for i in range(2)]
    assert rows[1] > rows[0]                                         # its foot comes down the image as it nears
    plain = render_all(scene, cfg, pos, np.zeros(2), np.zeros(2), ["summer"] * 2, np.zeros(2, int),
                       np.random.default_rng(0))
    changed = (plain != imgs).any(-1)
    assert not changed[lab != DISTRACTOR_LABEL].any()                # nothing else moved (noise draws included)


def test_distractor_rate_is_checked_and_neutral_in_the_fingerprint():
    assert make_config("city", distractor_rate=0.0).fingerprint() == make_config("city").fingerprint()
    assert make_config("city", distractor_rate=1.0).fingerprint() != make_config("city").fingerprint()
    with pytest.raises(ValueError, match="distractor_rate"):
        make_config("city", distractor_rate=-1.0)
    with pytest.raises(ValueError, match="labels"):
        make_dataset("city", 0, labels="yes")


def test_take_queries_slices_every_query_field_and_keeps_the_missing_ones():
    tr = make_dataset("city", 0, blocks=(3, 2)).train
    sub = tr.take_queries(np.array([0, 2]))
    assert len(sub.q_images) == 2 and sub.q_labels is None and sub.db_images is tr.db_images
    assert np.array_equal(sub.q_utm, tr.q_utm[[0, 2]])
    assert np.array_equal(tr.take_queries(np.arange(len(tr.q_utm)) < 3).q_heading, tr.q_heading[:3])
    with pytest.raises(ValueError, match="outside"):
        tr.take_queries(np.array([len(tr.q_utm)]))
