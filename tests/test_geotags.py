"""Geotags are checked at load (vpr_nb.datasets.geotags): an impossible position raises ValueError naming the
file, the row and the likely cause; an implausible one is named in a warning; valid data loads silently.

Each test copies a tiny fixture of data_fixtures/ into tmp_path and breaks its geotags one way.
"""
import warnings
from pathlib import Path

import numpy as np
import pytest

from dataset_fixtures import FIX, MF
from dataset_fixtures import copy_fixture as _copy
from dataset_fixtures import edit_lines as _edit
from vpr_nb import datasets as D



def _edit_row(path, row, fn):
    """Replace the fields of CSV data row ``row`` (1-based) by ``fn(fields)``."""
    _edit(path, lambda ls: ls[:row] + [",".join(fn(ls[row].split(",")))] + ls[row + 1:])


# --------------------------------------------------------------------------------------------- valid data
def test_the_fixtures_load_without_a_warning():
    loads = [(FIX / "pitts" / "datasets" / f"pitts30k_{p}.mat", "pitts", {}) for p in ("train", "val", "test")]
    loads += [(FIX / "gmberton" / "pitts30k", "gmberton", {}), (FIX / "msls", "msls", {}),
              (FIX / "msls_val_only", "msls", {"val_subset": "official"}), (FIX / "gsv_cities", "gsv-cities", {}),
              (FIX / "nordland", "nordland", {})]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for root, fmt, kw in loads:
            assert D.load(root, fmt, **kw).num_db > 0


def test_gmberton_dummy_positions_without_a_zone_are_not_utm(tmp_path):
    """gmberton's Nordland download names images @0@<north>@@@@@<frame>@...: dummy positions, no UTM zone."""
    base = tmp_path / "nordland" / "images" / "test"
    for f in range(12):
        MF.write_jpeg(base / "database" / f"@0@{f * 2.38:.2f}@@@@@{f}@@@@@@@@.jpg", f)
    MF.write_jpeg(base / "queries" / "@0@11.90@@@@@5@@@@@@@@.jpg", 99)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = D.load(tmp_path / "nordland", "gmberton")
    assert s.num_db == 12 and s.db_utm[:, 0].max() == 0.0


# --------------------------------------------------------------------------------------------- Pittsburgh
def _pitts_mat(tmp_path, db_utm=None, q_utm=None):
    root = _copy("pitts", tmp_path)
    s = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    db = [str(Path(p).relative_to(FIX / "pitts")) for p in s.db_paths]
    q = [str(Path(p).relative_to(FIX / "pitts" / "queries_real")) for p in s.q_paths]
    path = root / "datasets" / "bad_pitts30k_test.mat"
    MF.write_pitts_mat(path, MF.pitts_fields(db, s.db_utm if db_utm is None else db_utm, q,
                                             s.q_utm if q_utm is None else q_utm))
    return path, s


def test_pitts_swapped_utm_rows_raise_naming_the_entry_and_the_cause(tmp_path):
    ref = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    path, _ = _pitts_mat(tmp_path, db_utm=ref.db_utm[:, ::-1])   # utmDb saved as (northing; easting)
    with pytest.raises(ValueError, match=r"bad_pitts30k_test\.mat: dbStruct field 2 \(utmDb\), entry 0 "
                                         r"\(000/000000_pitch1_yaw1\.jpg\): UTM easting=4477000\.00 m, "
                                         r"northing=584000\.00 m is impossible.*\(8 position\(s\) in all\); easting "
                                         r"and northing look exchanged.*: utmDb rows swapped\?"):
        D.load(path, "pitts")


def test_pitts_query_in_degrees_or_far_away(tmp_path):
    ref = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    q = ref.q_utm.copy()
    q[2] = (-79.99, 40.44)                                       # lon/lat of Pittsburgh, not UTM metres
    path, _ = _pitts_mat(tmp_path / "a", q_utm=q)
    with pytest.raises(ValueError, match=r"field 4 \(utmQ\), entry 2 \(000/000053_pitch1_yaw1\.jpg\).*"
                                         r"latitude/longitude degrees instead of UTM metres\?"):
        D.load(path, "pitts")
    q[2] = ref.q_utm[2] + (0.0, 500_000.0)                       # a valid UTM position, 500 km north
    path, _ = _pitts_mat(tmp_path / "b", q_utm=q)
    with pytest.warns(UserWarning, match=r"bad_pitts30k_test\.mat: 1 image\(s\) lie more than 100,000 m from the "
                                         r"median position of their city \(e\.g\. queries_real/000/000053_pitch1_"
                                         r"yaw1\.jpg, 500\.0 km"):
        D.load(path, "pitts")


# --------------------------------------------------------------------------------------------- gmberton
@pytest.mark.parametrize("east, north, match", [
    (5440000.32, 4177609.18, r"UTM east=5440000\.32 m, north=4177609\.18 m is impossible.*a mistyped"),
    (4177609.18, 544000.32, r"is impossible.*fields 1 and 2 \(UTM east, north\) swapped\?"),
    (544000.32, -4177609.18, r"north=-4177609\.18 m is impossible"),
])
def test_gmberton_impossible_utm_raises_naming_the_file(tmp_path, east, north, match):
    root = _copy("gmberton", tmp_path) / "pitts30k"
    name = MF.gmberton_name(east, north, 90, "bad", lat=37.74472, lon=-122.50057)
    MF.write_jpeg(root / "images" / "test" / "queries" / name, 1)
    with pytest.raises(ValueError, match=match) as err:
        D.load(root, "gmberton")
    assert name in str(err.value)


def test_gmberton_zone_and_latlon_are_checked(tmp_path):
    root = _copy("gmberton", tmp_path) / "pitts30k"
    q = root / "images" / "test" / "queries"
    bad = q / MF.gmberton_name(544000.32, 4177609.18, 90, "z", zone=99)
    MF.write_jpeg(bad, 1)
    with pytest.raises(ValueError, match=r"@99@S@.*field 3 \(UTM zone\) '99' is not a UTM zone number"):
        D.load(root, "gmberton")
    bad.unlink()
    MF.write_jpeg(q / MF.gmberton_name(544000.32, 4177609.18, 90, "ll", lat=-122.50057, lon=37.74472), 1)
    with pytest.raises(ValueError, match=r"field 5 \(latitude\): -122\.501 is outside \[-90, 90\] degrees.*"
                                         r"latitude and longitude swapped\?"):
        D.load(root, "gmberton")


def test_gmberton_lone_image_far_from_all_others_warns(tmp_path):
    root = _copy("gmberton", tmp_path) / "pitts30k"
    name = MF.gmberton_name(544000.32, 4477609.18, 90, "typo", lat=37.74472, lon=-122.50057)   # 300 km north
    MF.write_jpeg(root / "images" / "test" / "queries" / name, 1)
    with pytest.warns(UserWarning, match=r"1 image\(s\) have no other image within 100,000 m \(e\.g\. "
                                         + name.replace(".", r"\.") + r" at easting 544000\.32, northing "
                                         r"4477609\.18 m, 300\.0 km from the nearest other\)"):
        s = D.load(root, "gmberton")
    assert s.num_q == 4


# --------------------------------------------------------------------------------------------- MSLS
def test_msls_impossible_easting_raises_naming_file_row_and_key(tmp_path):
    root = _copy("msls", tmp_path)
    post = root / "train_val" / "sf" / "database" / "postprocessed.csv"
    key = post.read_text().splitlines()[3].split(",")[1]
    _edit_row(post, 3, lambda f: f[:2] + [f[3], f[2]] + f[4:])   # data row 3: easting and northing exchanged
    with pytest.raises(ValueError, match=r"sf/database/postprocessed\.csv: column 'easting', data row 3 \(line 4, "
                                         rf"key {key}\): UTM easting=4181000\.00 m, northing=551200\.00 m is "
                                         r"impossible.*columns 'easting' and 'northing' swapped\?"):
        D.load(root, "msls")


def test_msls_impossible_latitude_in_raw_csv_raises(tmp_path):
    root = _copy("msls", tmp_path)
    raw = root / "train_val" / "cph" / "query" / "raw.csv"
    _edit_row(raw, 2, lambda f: f[:3] + ["155.676"] + f[4:])
    with pytest.raises(ValueError, match=r"cph/query/raw\.csv: column 'lat', data row 2 \(line 3, key \S+\): "
                                         r"155\.676 is outside \[-90, 90\] degrees"):
        D.load(root, "msls")


def test_msls_lone_image_far_from_its_city_warns(tmp_path):
    root = _copy("msls", tmp_path)
    post = root / "train_val" / "cph" / "database" / "postprocessed.csv"
    _edit_row(post, 2, lambda f: f[:3] + ["6676000.000"] + f[4:])   # northing 500 km off: still valid UTM
    with pytest.warns(UserWarning, match=r"cph/database/postprocessed\.csv: 1 image\(s\) have no other image within "
                                         r"100,000 m \(e\.g\. key \S+ \(data row 2\)"):
        D.load(root, "msls", cities="val")


# --------------------------------------------------------------------------------------------- GSV-Cities
def test_gsv_image_with_lat_lon_swapped_is_named(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    csv = root / "Dataframes" / "PRS.csv"
    _edit_row(csv, 6, lambda f: f[:5] + [f[6], f[5]] + f[7:])      # place 1, second image: (lon, lat)
    with pytest.warns(UserWarning) as rec:
        s = D.load(root, "gsv-cities", check_files=False)
    msgs = [str(w.message) for w in rec]
    assert len(msgs) == 1, msgs                                     # the city check does not repeat it
    assert "PRS.csv (GSV-Cities city 'PRS'): 1 image(s) lie more than 1,000 m from the median position of " \
           "their place (e.g. PRS_0000001_2011_04_055_2.35319_48.85861_" in msgs[0]
    assert "(data row 6)" in msgs[0] and "latitude and longitude swapped?" in msgs[0]
    assert s.num_db == 17


def test_gsv_city_spanning_thousands_of_km_warns(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    csv = root / "Dataframes" / "PRS.csv"
    _edit(csv, lambda ls: [ls[0]] + [ln.replace(",48.8", ",18.8") if ln.startswith("0,") else ln for ln in ls[1:]])
    with pytest.warns(UserWarning, match=r"PRS\.csv \(GSV-Cities city 'PRS'\): 4 image\(s\) lie more than 100,000 m "
                                         r"from the median position of their city \(e\.g\. PRS_0000000_\S+_18\.8566\S* "
                                         r"\(data row \d\), 3,\d{3}\.\d km from that of city PRS\).*wrong city\?") as rec:
        D.load(root, "gsv-cities", check_files=False)
    assert not any("swapped" in str(w.message) for w in rec)


def test_gsv_latitude_beyond_utm_says_when_lat_lon_look_swapped(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    csv = root / "Dataframes" / "OSL.csv"
    _edit_row(csv, 3, lambda f: f[:5] + ["100.5", "13.75"] + f[7:])   # Bangkok's (lon, lat) in the lat, lon columns
    with pytest.raises(ValueError, match=r"OSL\.csv: column 'lat', data row 3 \(line 4\): 100\.5 is outside \[-84, 84\] "
                                         r"degrees \(1 row\(s\) in all\); UTM covers 84 S to 84 N: latitude and "
                                         r"longitude swapped\?"):
        D.load(root, "gsv-cities")


# --------------------------------------------------------------------------------------------- the checks
def test_check_utm_and_isolation_directly():
    from vpr_nb.datasets import geotags as G

    where = lambda i, c: f"row {i} ({c})"  # noqa: E731
    G.check_utm(np.array([[166_021.0, 0.0], [833_979.0, 9_329_000.0]]), where, swap_hint="x")
    G.check_utm(np.array([[0.0, 5.0]]), where, swap_hint="x", rows=[False])   # not UTM: not checked
    with pytest.raises(ValueError, match=r"row 1 \(northing\).*2 position\(s\) in all"):
        G.check_utm(np.array([[500_000.0, 0.0], [500_000.0, 1e7 + 1], [50.0, 1.0]]), where, swap_hint="x")
    G.warn_isolated(np.zeros((0, 2)), "src", str)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        G.warn_isolated(np.array([[0.0, 0.0], [0.0, 90_000.0], [0.0, 180_000.0]]), "src", str)   # a route
    with pytest.warns(UserWarning, match=r"src: 1 image\(s\) .* \(e\.g\. 2 at"):
        G.warn_isolated(np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 250_000.0]]), "src", str)
