"""Tests of the synthetic VPR world (vpr_nb.synthetic): determinism, shapes, splits, positives, bad input,
world kinds as records, the config's fingerprint, pinned pixels.

Worlds are kept small (few blocks / frames, 8×12-pixel images where pixels do not matter) so the
whole file runs in a few seconds.
"""
import dataclasses
import hashlib

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from vpr_nb.synthetic import (CONDITIONS, SPLITS, WORLD_KINDS, VPRDataset, WorldConfig, make_config, make_dataset,
                               world_kind)

SMALL_CITY = dict(blocks=(5, 2))          # 5 blocks so that every split (incl. val) is non-empty
SMALL_ROUTE = dict(num_frames=120)
GEOMETRY_ONLY = dict(image_size=(8, 12))  # tiny pixels: tests of geometry only


@pytest.fixture(scope="module")
def city():
    return make_dataset("city", seed=0, **SMALL_CITY)


@pytest.fixture(scope="module")
def route():
    return make_dataset("route", seed=0, **SMALL_ROUTE)


# ------------------------------------------------------------------------------------- determinism
@pytest.mark.parametrize("preset, overrides", [("city", dict(blocks=(3, 2))), ("route", SMALL_ROUTE)])
def test_same_seed_gives_identical_arrays(preset, overrides):
    a = make_dataset(preset, seed=3, image_size=(16, 24), **overrides)
    b = make_dataset(preset, seed=3, image_size=(16, 24), **overrides)
    for name in ("db_images", "q_images", "db_utm", "q_utm", "db_heading", "q_heading",
                 "db_condition", "q_condition", "db_split", "q_split", "db_place", "q_place"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("preset, overrides", [("city", dict(blocks=(3, 2))), ("route", SMALL_ROUTE)])
def test_different_seed_gives_different_world(preset, overrides):
    a = make_dataset(preset, seed=0, image_size=(16, 24), **overrides)
    b = make_dataset(preset, seed=1, image_size=(16, 24), **overrides)

    def differs(x, y):  # counts may differ too (cameras near the split gaps), compare the overlap
        m = min(len(x), len(y))
        return x.shape != y.shape or not np.array_equal(x[:m], y[:m])

    assert differs(a.q_images, b.q_images) and differs(a.q_utm, b.q_utm)
    m = min(len(a.db_images), len(b.db_images))
    assert not np.array_equal(a.db_images[:m], b.db_images[:m])   # other buildings / track
    if preset == "route":  # the route's track itself is random (the city's street grid is fixed)
        assert not np.allclose(a.db_utm[:m], b.db_utm[:m])


def test_rendering_one_split_matches_rendering_all(city):
    full = city.test
    only = make_dataset("city", seed=0, splits=("test",), **SMALL_CITY).test
    np.testing.assert_array_equal(full.db_images, only.db_images)
    np.testing.assert_array_equal(full.q_images, only.q_images)
    np.testing.assert_array_equal(full.q_utm, only.q_utm)


# ------------------------------------------------------------------------------- shapes and dtypes
@pytest.mark.parametrize("name", ["city", "route"])
def test_shapes_and_dtypes(name, city, route):
    ds = {"city": city, "route": route}[name]
    assert isinstance(ds, VPRDataset)
    h, w = ds.config.image_size
    n_db, n_q = len(ds.db_images), len(ds.q_images)
    assert n_db > 0 and n_q > 0
    for imgs, n in ((ds.db_images, n_db), (ds.q_images, n_q)):
        assert imgs.dtype == np.uint8 and imgs.shape == (n, h, w, 3)
    for utm, n in ((ds.db_utm, n_db), (ds.q_utm, n_q)):
        assert utm.shape == (n, 2) and np.issubdtype(utm.dtype, np.floating) and np.isfinite(utm).all()
    for f in ("heading", "condition", "split", "place"):
        assert getattr(ds, "db_" + f).shape == (n_db,)
        assert getattr(ds, "q_" + f).shape == (n_q,)
    assert ((ds.db_heading >= 0) & (ds.db_heading < 360)).all()
    assert (ds.db_condition == 0).all()                       # database: the reference condition
    assert ds.q_condition.min() >= 0 and ds.q_condition.max() < len(ds.condition_names)
    assert set(np.unique(ds.db_split)) <= {0, 1, 2} and set(np.unique(ds.q_split)) <= {0, 1, 2}
    assert ds.db_images.std() > 5                             # not blank images
    assert len(ds) == n_db + n_q and "VPRDataset" in repr(ds)


def test_image_size_override_and_split_subsets(city):
    small = make_dataset("city", image_size=(16, 24), blocks=(3, 2))
    assert small.db_images.shape[1:] == (16, 24, 3)
    parts = [city.split(s) for s in SPLITS]
    assert sum(len(p.db_images) for p in parts) == len(city.db_images)
    assert sum(len(p.q_images) for p in parts) == len(city.q_images)
    assert city.test.split_name == "test" and city.train is not None and city.val is not None


# ------------------------------------------------------------------------- geographically disjoint
@pytest.mark.parametrize("preset", ["city", "route"])
def test_splits_do_not_overlap_geographically(preset):
    ds = make_dataset(preset, **GEOMETRY_ONLY)   # the default tiny geometry, pixels shrunk
    pos = {s: np.concatenate([ds.db_utm[ds.db_split == s], ds.q_utm[ds.q_split == s]]) for s in range(3)}
    assert all(len(p) for p in pos.values()), "every split of the tiny world must be non-empty"
    for a, b in ((0, 1), (0, 2), (1, 2)):
        gap = cdist(pos[a], pos[b]).min()
        assert gap > ds.pos_radius, f"{SPLITS[a]} and {SPLITS[b]} are only {gap:.1f} m apart"
    # consequence: a query's positives always lie in its own split
    positives = ds.positives()
    for qi, p in enumerate(positives):
        assert (ds.db_split[p] == ds.q_split[qi]).all()


# ------------------------------------------------------------------------------------- positives
def test_city_positives_within_25_m(city):
    assert city.pos_radius == 25.0
    test = city.test
    positives = test.positives()
    d = cdist(test.q_utm, test.db_utm)
    for qi, p in enumerate(positives):
        assert p.tolist() == np.flatnonzero(d[qi] <= 25.0).tolist()
    counts = np.array([len(p) for p in positives])
    assert counts.min() >= 1                       # every query of the city has a positive
    # several headings per place: positives include more than one heading
    q0 = int(np.argmax(counts))
    assert len(np.unique(np.round(test.db_heading[positives[q0]] / 90))) > 1


def test_route_positives_are_plus_minus_one_frame():
    # without jitter the query sits on its frame: positives are exactly frames i-1, i, i+1
    ds = make_dataset("route", position_jitter=0.0, **SMALL_ROUTE, **GEOMETRY_ONLY)
    assert ds.pos_radius == pytest.approx(1.01 * ds.config.frame_spacing)
    for s in SPLITS:
        part = ds.split(s)
        n = len(part.db_images)
        assert len(part.q_images) == n                    # frame-aligned database and queries
        for i, p in enumerate(part.positives()):
            assert p.tolist() == [j for j in (i - 1, i, i + 1) if 0 <= j < n]
    # with the default along-track jitter only the rendered camera moves; the geotag stays on the
    # frame, so positives are still exactly frames i-1, i, i+1
    ds = make_dataset("route", **SMALL_ROUTE, **GEOMETRY_ONLY)
    for s in SPLITS:
        part = ds.split(s)
        n = len(part.db_images)
        for i, p in enumerate(part.positives()):
            assert p.tolist() == [j for j in (i - 1, i, i + 1) if 0 <= j < n]


def test_route_conditions_summer_vs_winter(route):
    assert route.condition_names == ("summer", "winter")
    assert (route.q_condition == 1).all()


# ------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs, match", [
    (dict(preset="desert"), "unknown preset"),
    (dict(size="huge"), "unknown size"),
    (dict(fog_density=3.0), "unknown world option"),
    (dict(position_jitter=-1.0), "position_jitter"),
    (dict(heading_jitter=-0.5), "heading_jitter"),
    (dict(occluder_rate=-1.0), "occluder_rate"),
    (dict(condition_strength=1.5), "condition_strength"),
    (dict(num_facade_types=0), "num_facade_types"),
    (dict(split_fractions=(0.5, 0.5, 0.5)), "split_fractions"),
    (dict(split_fractions=(0.5, 0.5)), "split_fractions"),
    (dict(split_fractions=(1.0, 0.0, 0.0)), "split_fractions"),
    (dict(image_size=(4, 48)), "image_size"),
    (dict(image_size=(32, 1000)), "image_size"),
    (dict(query_conditions=("monsoon",)), "unknown condition"),
    (dict(seed=-1), "seed"),
    (dict(seed=1.5), "seed"),
    (dict(splits=("train", "holdout")), "splits"),
    (dict(splits=()), "splits"),
    (dict(building_height=(26.0, 6.0)), "building_height"),
    (dict(tree_radius=(1.0,)), "tree_radius"),
    (dict(car_share=1.5), "car_share"),
    (dict(headings=0), "headings"),
    (dict(sky_radius=0.0), "sky_radius"),
    (dict(zone_house_share=(0.1, 0.2)), "zone tables"),
    (dict(zone_fence_share=(0.0, 1.5, 0.0)), "zone shares"),
    (dict(preset="route", track_smoothing=500), "track_smoothing"),
    (dict(preset="route", size="huge"), "unknown size"),
    (dict(preset="route", camera_yaw=200.0), "camera_yaw"),
    (dict(preset="route", roadside_spacing=-1.0), "roadside_spacing"),
    (dict(preset="route", roadside_height=(3.0, 1.0)), "roadside_height"),
])
def test_make_dataset_rejects_bad_input(kwargs, match):
    kwargs = {"preset": "city", **kwargs}
    with pytest.raises(ValueError, match=match):
        make_dataset(**kwargs)


def test_make_config_and_worldconfig_reject_bad_input():
    with pytest.raises(ValueError, match="unknown preset"):
        make_config("desert")
    with pytest.raises(ValueError, match="unknown size"):
        make_config("city", "huge")
    with pytest.raises(ValueError, match="unknown world option"):
        make_config("city", jitter=1.0)
    with pytest.raises(ValueError, match="unknown preset"):
        WorldConfig(preset="desert")
    cfg = make_config("route")
    assert cfg.pos_radius == pytest.approx(1.01 * cfg.frame_spacing)


def test_split_rejects_unknown_and_unrendered(city):
    with pytest.raises(ValueError, match="unknown split"):
        city.split("holdout")
    only_test = make_dataset("city", splits=("test",), **SMALL_CITY, **GEOMETRY_ONLY)
    with pytest.raises(ValueError, match="empty"):
        only_test.split("train")


@pytest.mark.parametrize("preset", ["city", "route"])
def test_few_facade_types_render(preset):
    # num_facade_types >= 1 is accepted by WorldConfig, so every such value must render
    ds = make_dataset(preset, num_facade_types=1, **SMALL_ROUTE, blocks=(3, 2), **GEOMETRY_ONLY)
    assert ds.db_images.shape[0] > 0


# ------------------------------------------------------------------------------ pixels, pinned
# sha256 of db_images + q_images, recorded with the renderer as it was before it was split into stages
# (vpr_nb.synthetic.render._render, issue 14). Every notebook number depends on these pixels: a change of
# the renderer that changes a single bit must be deliberate, and then re-record the hash here and re-run
# the reproduce profile (the committed results are keyed on the world config, not on rendering constants).
PINNED_WORLDS = {
    # every city query condition (overcast, dusk: lit windows, autumn, winter: snow, rain); walls and trees
    "city": (dict(seed=5, blocks=(3, 2), image_size=(24, 32)),
             "49730d032b80ebf3e927eb5695ee0a54873d84cd5959d70da54026ebca5385f1"),
    # the route's ground (grass, ballast, rails) and all four materials: houses, trees, poles, fences
    # (without the content near the camera, which the route has by default since: pinned on its own below)
    "route": (dict(seed=6, num_frames=60, image_size=(24, 32), query_conditions=("winter", "dusk", "rain"),
                   condition_strength=1.0, roadside_spacing=0.0, camera_yaw=0.0),
              "9d7f64a5db6d04a9802d15781ec21aa135841f6cf0256b4aaf41748dc64b7118"),
    "route, default content": (dict(seed=6, num_frames=60, image_size=(24, 32), query_conditions=("winter",)),
                               "fcd8231bf335d6c51d0c36a91c98c39df303849989b848fa1a0e69c5e2d7771c"),
}


@pytest.mark.parametrize("preset", sorted(PINNED_WORLDS))
def test_rendered_pixels_are_pinned(preset):
    overrides, expected = PINNED_WORLDS[preset]
    ds = make_dataset(preset.split(",")[0], **overrides)
    kinds = set(np.unique(ds.extra["scene"].kind).tolist())
    assert kinds >= ({0, 1} if preset == "city" else {0, 1, 2, 3}), f"the pinned {preset} world lost materials: {kinds}"
    digest = hashlib.sha256(np.ascontiguousarray(ds.db_images).tobytes()
                            + np.ascontiguousarray(ds.q_images).tobytes()).hexdigest()
    assert digest == expected, (f"the {preset} world renders other pixels than the pinned ones "
                                f"(sha256 {digest}, pinned {expected}): if that is deliberate, re-record the hash "
                                f"and re-run the reproduce profile (make reproduce)")


# ------------------------------------------------------------------------------- world kinds, records
def test_world_kinds_are_records_with_their_own_fields():
    names = {f.name for f in dataclasses.fields(WorldConfig)}
    seen = set()
    for name, kind in WORLD_KINDS.items():
        assert kind.name == name and world_kind(name) is kind
        assert kind.fields <= names, f"{name}: fields that WorldConfig lacks: {sorted(kind.fields - names)}"
        assert not kind.fields & seen, f"{name} claims fields of another kind: {sorted(kind.fields & seen)}"
        seen |= kind.fields
        assert set(kind.preset) <= names and all(set(v) <= names for v in kind.sizes.values())
        assert "tiny" in kind.sizes
        assert make_config(name).preset == name
    with pytest.raises(ValueError, match="unknown preset"):
        world_kind("desert")


def _changed(v):
    """Another valid value of a knob: integers + 1, floats x 0.8 (ranges keep low <= high, shares stay shares)."""
    if isinstance(v, tuple):
        return tuple(_changed(x) for x in v)
    return v + 1 if isinstance(v, int) else v * 0.8


def _other_kinds_fields(preset: str) -> dict:
    """Every field that only the other kinds read, set to another valid value."""
    cfg = make_config(preset)
    return {f: _changed(getattr(cfg, f)) for kind in WORLD_KINDS.values() if kind.name != preset for f in kind.fields}


@pytest.mark.parametrize("preset, overrides", [("city", dict(blocks=(3, 2))), ("route", SMALL_ROUTE)])
def test_a_kind_ignores_the_fields_of_the_other_kinds(preset, overrides):
    """What a record's ``fields`` says: the other kinds' knobs change nothing in this kind's world."""
    other = {k: v for k, v in _other_kinds_fields(preset).items() if k not in overrides}
    assert other, "the other kinds have own fields"
    a = make_dataset(preset, seed=2, **overrides, **GEOMETRY_ONLY)
    b = make_dataset(preset, seed=2, **overrides, **GEOMETRY_ONLY, **other)
    for name in ("db_images", "q_images", "db_utm", "q_utm", "db_heading", "q_heading", "db_split", "q_split",
                 "db_place", "q_place"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.extra["scene"].a, b.extra["scene"].a)


def test_a_new_world_kind_is_a_record_and_one_registry_line(monkeypatch):
    """A kind reusing the city's layout with its own deviations: registering the record is all it takes."""
    city = WORLD_KINDS["city"]
    suburb = dataclasses.replace(city, name="suburb", preset={"building_height": (4.0, 7.0), "street_tree_share": 0.9},
                                 sizes={"tiny": {"blocks": (3, 2)}})
    monkeypatch.setitem(WORLD_KINDS, "suburb", suburb)
    ds = make_dataset("suburb", seed=1, **GEOMETRY_ONLY)
    cfg = ds.config
    assert ds.name == "suburb-tiny" and cfg.preset == "suburb" and cfg.building_height == (4.0, 7.0)
    walls = ds.extra["scene"].kind == 0
    assert ds.extra["scene"].z1[walls].max() <= 7.0
    ref = make_dataset("city", seed=1, blocks=(3, 2), **GEOMETRY_ONLY)
    assert (ds.extra["scene"].kind == 1).sum() > (ref.extra["scene"].kind == 1).sum()   # more street trees
    np.testing.assert_array_equal(ds.db_utm, ref.db_utm)                                  # same street grid


def test_route_preset_and_sizes_come_from_its_record():
    route = WORLD_KINDS["route"]
    cfg = make_config("route", "small")
    assert cfg.num_frames == route.sizes["small"]["num_frames"] and cfg.query_conditions == ("winter",)
    assert cfg.pos_radius == pytest.approx(route.pos_radius_frames * cfg.frame_spacing) == cfg.train_pos_radius
    assert make_config("route", frame_spacing=2.5).pos_radius == pytest.approx(1.01 * 2.5)
    assert make_config("route", pos_radius=30.0).pos_radius == 30.0
    assert make_config("city", "small").blocks == WORLD_KINDS["city"].sizes["small"]["blocks"]


def test_roadside_content_and_sideways_camera():
    """The route's content knobs: roadside objects beside the track and a camera turned to the side.
    With them on, the frame 5 m ahead is a near-duplicate of a frame's cross-season positive far less
    often in pixels (vpr_nb.probes, Eq. (2)); with them off the world keeps its fingerprint."""
    from vpr_nb.probes import near_duplicate_probe

    off = dict(roadside_spacing=0.0, camera_yaw=0.0)
    plain = make_dataset("route", seed=1, frame_spacing=2.5, **SMALL_ROUTE, **off)
    rich = make_dataset("route", seed=1, frame_spacing=2.5, **SMALL_ROUTE)      # the route's defaults: on
    assert (rich.config.roadside_spacing, rich.config.camera_yaw) == (1.0, 45.0)
    np.testing.assert_array_equal(plain.db_utm, rich.db_utm)                  # same track and frames
    np.testing.assert_allclose((rich.db_heading - plain.db_heading) % 360, 45.0)
    pole = 2                                                                    # layout.POLE
    scene, before = rich.extra["scene"], (plain.extra["scene"].kind == pole).sum()
    objects = np.flatnonzero(scene.kind == pole)[before:]   # the roadside objects come after the catenary poles
    length = SMALL_ROUTE["num_frames"] * 2.5
    assert 0.8 * 2 * length < len(objects) < 1.2 * 2 * length                # one per metre per side
    mid = (scene.a[objects] + scene.b[objects]) / 2
    dist = cdist(mid, scene.layout["track"]).min(1)
    lo, hi = rich.config.roadside_distance
    assert dist.min() > lo - 0.1 and dist.max() < np.hypot(hi, 2.5)
    rates = [near_duplicate_probe(d.split("train"), None, steps=(5.0,))[5.0] for d in (plain, rich)]
    assert rates[0] > 0.8 and rates[1] < 0.6, rates
    assert make_config("route", **off).fingerprint() != make_config("route").fingerprint()
    assert dataclasses.replace(rich.config, **off).fingerprint() == plain.config.fingerprint()
    # with the knobs off nothing is drawn: the world is pixel for pixel the plain one
    np.testing.assert_array_equal(make_dataset("route", seed=1, frame_spacing=2.5, roadside_height=(1.0, 2.0),
                                               **SMALL_ROUTE, **off).db_images, plain.db_images)


def test_fingerprint_follows_every_field_and_the_condition_rows(monkeypatch):
    base = make_config("city")
    assert base.fingerprint() == make_config("city").fingerprint()
    assert base.fingerprint() != make_config("route").fingerprint()
    for f in ("fov", "building_height", "car_share", "house_every", "zone_fence_share"):
        assert dataclasses.replace(base, **{f: _changed(getattr(base, f))}).fingerprint() != base.fingerprint(), f
    assert base.fingerprint() != make_config("city", query_conditions=("winter",)).fingerprint()
    city, route = base.fingerprint(), make_config("route").fingerprint()
    monkeypatch.setitem(CONDITIONS, "dusk", dict(CONDITIONS["dusk"], lit=0.5))   # a row the city uses, the route not
    assert base.fingerprint() != city and make_config("route").fingerprint() == route
