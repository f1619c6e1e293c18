"""Tests of the route's density knob, ``camera_spacing`` (vpr_nb.synthetic.kinds.route): neutral when off
(pixels and geotags pinned as they were before the knob existed), denser frames along the same track with
smaller jitters when set, and clear errors for nonsense spacings."""
import hashlib

import numpy as np
import pytest

from vpr_nb.synthetic import WORLD_KINDS, make_config, make_dataset
from vpr_nb.synthetic.kinds.route import route_frames

NB07 = dict(num_facade_types=60, colour_variation=0.3, frame_spacing=2.5, frames_per_group=2)   # notebook 07's route
GEOMETRY_ONLY = dict(image_size=(8, 12))


def _sha(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


# sha256 of (db_images, q_images) and of (db_utm, q_utm, db_heading, q_heading), recorded before camera_spacing
# existed, with the pinned kernels of conftest.py (the geotags' last bits follow numpy's kernels). The whole tiny
# worlds (all splits) were checked too when the knob came: make_dataset("route", 0) images 44f21f1a14c93dfd...,
# geotags aac23cb7ab67f371...; notebook 07's route b6e0e1cce2fc9b13... / 96fc0a6d2c50f739...
PINNED = {
    "route, 120 frames": (dict(num_frames=120), None,
                          "a7ef7a9f958ca5a437c7ac1b364d9d9f90d414b47d2bbb6a92db0a53e3730d9c",
                          "22b73aff4f18954e0174a76e00253923c5ef9565fb6da6edb863f337458e29b0"),
    "route tiny, test split": (dict(size="tiny"), ("test",),
                               "abfc1d5b67e056066a0b82edd2409d5473496456c6bf51bb3bfbe099ba6708ac",
                               "361bcc34ba28bbde20f9b989c287f1238b5ab69e8ab836ad29e9a1e192996207"),
    "notebook 07's route, test split": (dict(size="tiny", **NB07), ("test",),
                                        "ca877df6a78fc0e983b169e7c36c2c62a26fd7ca17c4be37b6c5be6526d72527",
                                        "4a97e91ec92b45946b51ec29840f3de0f5cdd852f090e77aebb5e54ac9c5dc80"),
}
FINGERPRINTS = {   # make_config fingerprints recorded before the knob existed
    "tiny": ({}, "6e9c303c45680427e49dca125ab8acc857015e81971db7807da9f5c7ca15152b"),
    "120 frames": (dict(num_frames=120), "0df915ee3eff1b141a45b2b390c3d41f1e96c29490501d97e8edab49f369a1ea"),
    "notebook 07": (NB07, "8c8e36f7d06466f1e095ae9ff3d658731f4bc6f587be53934b4fe45e809f0c73"),
}


@pytest.mark.parametrize("name", sorted(PINNED))
def test_off_by_default_pixels_and_geotags_are_todays(name):
    overrides, splits, images, geotags = PINNED[name]
    ds = make_dataset("route", 0, **overrides, **({"splits": splits} if splits else {}))
    ds = ds.split(splits[0]) if splits else ds
    assert ds.config.camera_spacing == 0.0
    assert _sha(ds.db_images, ds.q_images) == images, f"{name}: other pixels than before camera_spacing"
    assert _sha(ds.db_utm, ds.q_utm, ds.db_heading, ds.q_heading) == geotags, f"{name}: other geotags"


@pytest.mark.parametrize("name", sorted(FINGERPRINTS))
def test_off_by_default_the_fingerprint_is_todays(name):
    overrides, expected = FINGERPRINTS[name]
    assert make_config("route", **overrides).fingerprint() == expected
    assert make_config("route", camera_spacing=1.0, **overrides).fingerprint() != expected


def test_spacing_equal_to_the_layouts_gives_the_same_world():
    off = make_dataset("route", 2, num_frames=80, **GEOMETRY_ONLY)
    same = make_dataset("route", 2, num_frames=80, camera_spacing=5.0, **GEOMETRY_ONLY)
    for f in ("db_images", "q_images", "db_utm", "q_utm", "db_heading", "q_heading", "db_split", "db_place"):
        np.testing.assert_array_equal(getattr(off, f), getattr(same, f), err_msg=f)


def _cameras(**overrides):
    """The scene and cameras of a route config, without rendering (make_dataset's streams)."""
    cfg = make_config("route", **overrides)
    geo, cam, _, _ = (np.random.default_rng(s) for s in np.random.SeedSequence(0).spawn(4))
    kind = WORLD_KINDS["route"]
    scene = kind.layout(cfg, geo)
    return cfg, scene, kind.cameras(cfg, cam, scene)


def test_denser_route_same_track_more_frames_per_metre_smaller_jitters():
    cfg0, scene0, off = _cameras(num_frames=300)
    cfg1, scene1, dense = _cameras(num_frames=300, camera_spacing=1.0)
    np.testing.assert_array_equal(scene0.a, scene1.a)                       # the same world, segment for segment
    np.testing.assert_array_equal(scene0.layout["track"], scene1.layout["track"])
    assert route_frames(cfg1) == (1.0, 299 * 5 + 1, 0.2) and route_frames(cfg0) == (5.0, 300, 1.0)
    assert len(dense.db_pos) == 1496 and len(off.db_pos) == 300               # 5x the frames over the same 1495 m
    np.testing.assert_allclose(dense.db_pos[::5], off.db_pos, atol=1e-9)     # every 5th frame is a frame of the off world
    steps = np.linalg.norm(np.diff(dense.db_pos, axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0, atol=1e-4)                        # one frame per metre, along the track
    assert cfg1.pos_radius == pytest.approx(1.01) and cfg0.pos_radius == pytest.approx(5.05)
    # the jitters scale with the spacing: position 0.8 m -> 0.16 m, heading 2 deg -> 0.4 deg (std)
    for cams, pos, head in ((off, 0.8, 2.0), (dense, 0.16, 0.4)):
        along = np.linalg.norm(cams.q_pos - cams.q_tag, axis=1)
        turn = (cams.q_heading - cams.db_heading + 180) % 360 - 180
        assert np.sqrt(np.mean(along ** 2)) == pytest.approx(pos, rel=0.15)
        assert np.std(turn) == pytest.approx(head, rel=0.15)
    # the splits stay bands of frames, a 2-frame gap wide, and place groups count camera frames
    assert {-1, 0, 1, 2} == set(np.unique(dense.db_split).tolist())
    assert np.array_equal(dense.db_place, np.arange(len(dense.db_pos)) // cfg1.frames_per_group)


def test_denser_world_positives_are_the_neighbouring_frames():
    ds = make_dataset("route", 0, num_frames=60, camera_spacing=2.0, splits=("test",), **GEOMETRY_ONLY).test
    n = len(ds.db_utm)
    assert ds.pos_radius == pytest.approx(2.02) and len(ds.q_utm) == n
    for i, pos in enumerate(ds.positives()):
        assert pos.tolist() == [j for j in (i - 1, i, i + 1) if 0 <= j < n]


@pytest.mark.parametrize("bad", [-1.0, -0.5, float("nan"), float("inf"), "1", True, None])
def test_nonsense_spacing_is_refused(bad):
    with pytest.raises(ValueError, match="camera_spacing must be a finite distance > 0"):
        make_config("route", camera_spacing=bad)


def test_spacing_that_does_not_fit_the_track_is_refused():
    with pytest.raises(ValueError, match="does not fit the track"):
        make_config("route", num_frames=10, camera_spacing=100.0)     # 45 m of track: one frame
    with pytest.raises(ValueError, match="does not fit the track"):
        make_dataset("route", 0, num_frames=10, camera_spacing=12.0)   # four frames, too few for three splits
    assert route_frames(make_config("route", num_frames=10, camera_spacing=1.0)).count == 46
