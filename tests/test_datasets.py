"""Tests of vpr_nb.datasets on the tiny real-format fixtures of data_fixtures/ and malformed variants of them."""
import importlib
import importlib.util
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from vpr_nb import datasets as D
from vpr_nb.image_tensors import IMAGENET_MEAN, IMAGENET_STD

FIX = Path(__file__).resolve().parents[1] / "data_fixtures"


def _make_fixtures_module():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIX / "make_fixtures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


MF = _make_fixtures_module()


def _pos(split, radius=None):
    return [p.tolist() for p in split.positives(radius)]


def _copy(name, tmp_path):
    dst = tmp_path / name
    shutil.copytree(FIX / name, dst)
    return dst


# --------------------------------------------------------------------------------------------- fixtures
def test_fixtures_are_small_and_reproducible(tmp_path):
    files = sorted(p.relative_to(FIX) for p in FIX.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    total = sum((FIX / p).stat().st_size for p in files)
    assert total < 1024 * 1024
    MF.main(tmp_path)
    made = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    # course_backbone.{pt,json} are written by `python -m vpr_nb.pretrain` (tests/test_pretrain.py)
    data = [p for p in files if p.suffix not in (".py", ".md") and not p.name.startswith("course_backbone.")]
    assert made == data
    from PIL import Image

    bad = {p for p in made if p.suffix == ".jpg" and D.find_unreadable_images([tmp_path / p])}
    assert len(bad) == 1 and MF.MSLS_TRUNCATED_CITY in str(next(iter(bad)))   # the one truncated JPEG
    assert D.find_unreadable_images([FIX / p for p in bad])
    for p in made:
        if p in bad:
            continue
        if p.suffix == ".jpg":  # JPEG bytes may depend on the libjpeg build: compare the pixels
            a = np.asarray(Image.open(tmp_path / p), dtype=np.int16)
            b = np.asarray(Image.open(FIX / p), dtype=np.int16)
            assert a.shape == b.shape and np.abs(a - b).max() <= 3, p
        else:
            assert (tmp_path / p).read_bytes() == (FIX / p).read_bytes(), p


# --------------------------------------------------------------------------------------------- Pittsburgh
def test_pitts_fixture():
    s = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    assert isinstance(s, D.GeoSplit) and s.format == "pitts" and s.name == "pitts30k_test"
    assert (s.num_db, s.num_q) == (8, 3)
    assert s.pos_radius == 25.0 and s.train_pos_radius == pytest.approx(10.0)
    assert s.db_utm.dtype == np.float64 and s.db_utm.shape == (8, 2)
    np.testing.assert_allclose(s.db_utm[2], [584015.0, 4477000.0])
    np.testing.assert_allclose(s.q_utm[1], [584060.0, 4477020.0])
    assert _pos(s) == [[0, 1, 2, 3], [4, 5], [6, 7]]
    assert _pos(s, 10.0) == [[0, 1, 2, 3], [], [6, 7]]  # inclusive: place 1 is exactly 10 m away
    assert _pos(s, 9.0) == [[0, 1], [], [6, 7]]
    assert s.db_paths[0].endswith("pitts/000/000000_pitch1_yaw1.jpg")
    assert "/queries_real/000/" in s.q_paths[0]
    assert all(Path(p).is_file() for p in s.db_paths + s.q_paths)
    assert s.extras["whichSet"] == "test" and s.extras["dataset"] == "pitts30k"
    assert s.extras["db_yaw"].tolist() == [1, 2] * 4 and s.extras["q_pitch"].tolist() == [1, 1, 1]


def _pitts_variant(tmp_path, mutate=None, **overrides):
    root = _copy("pitts", tmp_path)
    s = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    db = [str(Path(p).relative_to(FIX / "pitts")) for p in s.db_paths]
    q = [str(Path(p).relative_to(FIX / "pitts" / "queries_real")) for p in s.q_paths]
    fields = MF.pitts_fields(db, s.db_utm, q, s.q_utm)
    fields.update(overrides)
    if mutate:
        mutate(fields)
    path = root / "datasets" / "bad_pitts30k_test.mat"
    MF.write_pitts_mat(path, fields)
    return path


def test_pitts_images_root(tmp_path):
    mat = tmp_path / "pitts30k_test.mat"
    shutil.copy(FIX / "pitts" / "datasets" / "pitts30k_test.mat", mat)
    with pytest.raises(ValueError, match="images_root"):
        D.load(mat, "pitts")
    s = D.load(mat, "pitts", images_root=FIX / "pitts")
    assert s.num_db == 8 and Path(s.db_paths[0]).is_file()
    with pytest.raises(FileNotFoundError, match="images_root"):
        D.load(mat, "pitts", images_root=tmp_path / "nowhere")


def test_pitts_missing_image_named(tmp_path):
    path = _pitts_variant(tmp_path)
    (tmp_path / "pitts" / "000" / "000024_pitch1_yaw2.jpg").unlink()
    with pytest.raises(FileNotFoundError, match=r"1 listed image.*000/000024_pitch1_yaw2\.jpg"):
        D.load(path, "pitts")
    assert D.load(path, "pitts", check_files=False).num_db == 8


@pytest.mark.parametrize("kind, match", [
    ("few_fields", r"9 fields.*at least 10"),
    ("utm_shape", r"2 \(utmDb\) must be 2x8"),
    ("utm_nan", r"4 \(utmQ\) has NaN"),
    ("names_numeric", r"1 \(dbImageFns\) must be a cell array"),
    ("sq_thr", r"posDistSqThr=100.0 is not posDistThr\^2"),
    ("thr_text", r"7 \(posDistThr\) must be one number"),
])
def test_pitts_malformed_struct(tmp_path, kind, match):
    def mutate(f):
        if kind == "few_fields":
            del f["nonTrivPosDistSqThr"]
        elif kind == "utm_shape":
            f["utmDb"] = np.zeros((3, 8))
        elif kind == "utm_nan":
            f["utmQ"] = f["utmQ"].copy()
            f["utmQ"][0, 1] = np.nan
        elif kind == "names_numeric":
            f["dbImageFns"] = np.arange(8.0)
        elif kind == "sq_thr":
            f["posDistSqThr"] = 100.0
        elif kind == "thr_text":
            f["posDistThr"] = "25"
    path = _pitts_variant(tmp_path, mutate)
    with pytest.raises(ValueError, match=match) as err:
        D.load(path, "pitts")
    assert "bad_pitts30k_test.mat" in str(err.value)


def test_pitts_not_a_struct_and_missing(tmp_path):
    from scipy.io import savemat

    bad = tmp_path / "datasets" / "x.mat"
    bad.parent.mkdir()
    savemat(bad, {"something": np.zeros(3)})
    with pytest.raises(ValueError, match=r"x\.mat: no variable 'dbStruct'"):
        D.load(bad, "pitts")
    savemat(bad, {"dbStruct": np.zeros(3)})
    with pytest.raises(ValueError, match="1x1 MATLAB struct"):
        D.load(bad, "pitts")
    (tmp_path / "datasets" / "junk.mat").write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(ValueError, match=r"junk\.mat: not a readable"):
        D.load(tmp_path / "datasets" / "junk.mat", "pitts")
    with pytest.raises(FileNotFoundError, match="dbStruct file not found"):
        D.load(tmp_path / "datasets" / "absent.mat", "pitts")


def test_pitts_count_mismatch_warns(tmp_path):
    path = _pitts_variant(tmp_path, numImages=9.0)
    with pytest.warns(UserWarning, match="numImages/numQueries"):
        s = D.load(path, "pitts")
    assert s.num_db == 8


# --------------------------------------------------------------------------------------------- gmberton
def test_gmberton_fixture():
    s = D.load(FIX / "gmberton" / "pitts30k", "gmberton")
    assert (s.num_db, s.num_q, s.name) == (6, 3, "pitts30k_test")
    assert (s.pos_radius, s.train_pos_radius) == (25.0, 10.0)
    np.testing.assert_allclose(s.db_utm[0], [544000.32, 4177609.18])
    assert s.db_heading.tolist() == [0, 30, 60, 90, 120, 150]
    assert s.extras["db_zone"][0] == "10S" and s.extras["db_pano_id"][1] == "pano1"
    assert _pos(s) == [[0, 1], [3, 4], []]
    # the split folder itself is accepted too, and other splits are looked for
    s2 = D.load(FIX / "gmberton" / "pitts30k" / "images" / "test", "gmberton")
    assert s2.db_paths == s.db_paths
    with pytest.raises(FileNotFoundError, match=r"images/val/"):
        D.load(FIX / "gmberton" / "pitts30k", "gmberton", split="val")


def test_parse_gmberton_name():
    f = D.parse_gmberton_name("x/@0544000.32@4177609.18@10@S@037.74472@-122.50057@NY0V@@0@@@@201708@@.jpg")
    assert (f["east"], f["north"], f["zone"], f["letter"], f["pano_id"], f["heading"]) == \
        (544000.32, 4177609.18, "10", "S", "NY0V", 0.0)
    assert D.parse_gmberton_name("@0@123.5@@@@@77@@@@@@@@.jpg")["north"] == 123.5


@pytest.mark.parametrize("name, match", [
    ("plain_name.jpg", "not a gmberton '@' file name"),
    ("@nan@4177609.18@10@S@@@@@@@@@@@@.jpg", r"field 1 \(UTM_east\)"),
    ("@544000@north@10@S@@@@@@@@@@@@.jpg", r"field 2 \(UTM_north\) 'north' is not a number"),
    ("@544000@4177609@10@S@@@@@east@@@@@@.jpg", r"field 9 \(heading\)"),
])
def test_gmberton_malformed_names(tmp_path, name, match):
    root = _copy("gmberton", tmp_path) / "pitts30k"
    MF.write_jpeg(root / "images" / "test" / "queries" / name, 1)
    with pytest.raises(ValueError, match=match) as err:
        D.load(root, "gmberton")
    assert name in str(err.value)


def test_gmberton_missing_folders_and_broken_link(tmp_path):
    root = _copy("gmberton", tmp_path) / "pitts30k"
    qdir = root / "images" / "test" / "queries"
    link = qdir / MF.gmberton_name(544001.0, 4177609.0)
    link.symlink_to(tmp_path / "does_not_exist.jpg")
    with pytest.raises(FileNotFoundError, match="first: .*does_not_exist|first: .*@0544001.00"):
        D.load(root, "gmberton")
    link.unlink()
    for f in qdir.iterdir():
        f.unlink()
    with pytest.raises(ValueError, match="no images"):
        D.load(root, "gmberton")
    shutil.rmtree(qdir)
    with pytest.raises(FileNotFoundError, match="database,queries"):
        D.load(root, "gmberton")


# --------------------------------------------------------------------------------------------- MSLS
def test_msls_fixture_all_cities():
    s = D.load(FIX / "msls", "msls", cities=["cph", "sf", "trondheim"])
    assert s.extras["cities"] == ["cph", "sf", "trondheim"]
    # per city: 6 db with 1 pano -> 5; 5 queries with 1 pano -> 4
    assert (s.num_db, s.num_q) == (15, 12)
    assert s.extras["db_cluster"].tolist()[:5] == [1, 1, 2, 2, -1]
    assert s.extras["q_cluster"].tolist()[:4] == [1, 2, 2, 4]
    # places are (city, unique_cluster) pairs, numbered globally: the same cluster id in two cities differs
    assert s.db_place[0] == s.db_place[1] == s.q_place[0] and s.db_place[2] == s.q_place[1]
    assert s.db_place[4] == -1 and s.db_place[0] != s.db_place[2]
    cph, sf = s.db_region == "cph", s.db_region == "sf"
    assert not set(s.db_place[cph & (s.db_place >= 0)]) & set(s.db_place[sf & (s.db_place >= 0)])
    assert s.db_region.tolist()[:5] == ["cph"] * 5 and s.q_region[-1] == "trondheim"
    np.testing.assert_allclose(s.db_utm[1], [724005.0, 6176000.0])
    np.testing.assert_allclose(s.q_heading[:2], [0.0, 37.5])
    assert s.extras["q_night"][:2].tolist() == [False, True]
    assert s.extras["db_view_direction"][:3].tolist() == ["Forward", "Backward", "Sideways"]
    assert all(p.endswith(f"/images/{k}.jpg") for p, k in zip(s.q_paths, s.extras["q_key"]))
    assert _pos(s)[:4] == [[0, 1], [2, 3], [2, 3], []]
    assert _pos(s)[4] == [5, 6]  # sf queries match sf database only


def test_msls_val_official_subset_and_key_list(tmp_path):
    s = D.load(FIX / "msls", "msls", cities="val", val_subset="official")
    assert s.name == "msls_val" and s.extras["cities"] == ["cph", "sf"]
    # queries: pano, subtask all=False and no-positive ones dropped -> 2 per city
    assert (s.num_db, s.num_q) == (10, 4)
    assert all(len(p) > 0 for p in s.positives())
    keys = list(s.extras["q_key"])
    txt = tmp_path / "msls_val_queries.txt"
    txt.write_text("\n".join(f"train_val/cph/query/images/{k}.jpg" for k in keys) + "\n")
    s2 = D.load(FIX / "msls", "msls", cities="val", query_keys=txt)
    assert list(s2.extras["q_key"]) == keys
    npy = tmp_path / "qImages.npy"
    np.save(npy, np.array(keys[:3]))
    assert list(D.load(FIX / "msls", "msls", cities=["cph", "sf"], query_keys=npy).extras["q_key"]) == keys[:3]
    with pytest.raises(ValueError, match="either val_subset"):
        D.load(FIX / "msls", "msls", val_subset="official", query_keys=txt)
    with pytest.raises(FileNotFoundError, match="query key list"):
        D.load(FIX / "msls", "msls", query_keys=tmp_path / "none.txt")
    txt.write_text("nothing_matches\n")
    with pytest.raises(ValueError, match="none of its keys"):
        D.load(FIX / "msls", "msls", query_keys=txt)


def test_msls_options():
    s = D.load(FIX / "msls" / "train_val", "msls", cities=["trondheim"], exclude_panos=False)
    assert (s.num_db, s.num_q) == (6, 5) and s.name == "msls_trondheim"
    with pytest.raises(FileNotFoundError, match=r"\['boston'"):
        D.load(FIX / "msls", "msls", cities="train")
    with pytest.raises(ValueError, match="val_subset"):
        D.load(FIX / "msls", "msls", val_subset="740")
    with pytest.raises(FileNotFoundError, match="no train_val"):
        D.load(FIX / "gsv_cities", "msls")


def _rewrite_csv(path, fn):
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


@pytest.mark.parametrize("csv_name, edit, exc, match", [
    ("postprocessed.csv", lambda ls: [ls[0].replace("easting", "east")] + ls[1:], ValueError,
     r"postprocessed\.csv: missing column\(s\) \['easting'\]"),
    ("raw.csv", lambda ls: [ls[0].replace(",pano", ",is_pano")] + ls[1:], ValueError, r"raw\.csv: missing column"),
    ("postprocessed.csv", lambda ls: [ls[0], ",".join("nan" if i == 3 else v for i, v in enumerate(ls[1].split(",")))] + ls[2:], ValueError,
     r"postprocessed\.csv: column 'northing' is NaN/inf in 1 row"),
    ("postprocessed.csv", lambda ls: [ls[0], ls[1].replace(",1,", ",x,", 1)] + ls[2:], ValueError,
     r"column 'unique_cluster', data row 1"),
    ("raw.csv", lambda ls: ls[:-1], ValueError, r"does not list the same images"),
    ("raw.csv", lambda ls: [ls[0], ls[1].replace("False", "maybe")] + ls[2:], ValueError, r"'pano' must be True/False"),
    ("postprocessed.csv", lambda ls: [ls[0], ls[1] + ",extra"] + ls[2:], ValueError, r"line 2: 9 fields"),
    ("postprocessed.csv", lambda ls: [], ValueError, r"empty CSV"),
])
def test_msls_malformed_csv(tmp_path, csv_name, edit, exc, match):
    root = _copy("msls", tmp_path)
    _rewrite_csv(root / "train_val" / "sf" / "database" / csv_name, edit)
    with pytest.raises(exc, match=match) as err:
        D.load(root, "msls")
    assert "sf/database" in str(err.value)


def test_msls_missing_files(tmp_path):
    root = _copy("msls", tmp_path)
    img = sorted((root / "train_val" / "cph" / "query" / "images").iterdir())[0]
    img.unlink()
    with pytest.raises(FileNotFoundError, match=img.name):
        D.load(root, "msls")
    assert D.load(root, "msls", check_files=False).num_q == 20
    (root / "train_val" / "sf" / "query" / "subtask_index.csv").unlink()
    with pytest.raises(FileNotFoundError, match="subtask_index.csv"):
        D.load(root, "msls", val_subset="official", check_files=False)
    (root / "train_val" / "sf" / "query" / "raw.csv").unlink()
    with pytest.raises(FileNotFoundError, match=r"sf/query/raw\.csv"):
        D.load(root, "msls", check_files=False)


def test_msls_without_index_column(tmp_path):
    root = _copy("msls", tmp_path)
    for csv_path in (root / "train_val").rglob("*.csv"):
        _rewrite_csv(csv_path, lambda ls: [ln.split(",", 1)[1] for ls_ in [ls] for ln in ls_])
    s = D.load(root, "msls")
    ref = D.load(FIX / "msls", "msls")
    np.testing.assert_array_equal(s.q_utm, ref.q_utm)
    assert list(s.extras["q_key"]) == list(ref.extras["q_key"])


# --------------------------------------------------------------------------------------------- GSV-Cities
def test_gsv_fixture():
    s = D.load(FIX / "gsv_cities", "gsv-cities")
    assert s.extras["cities"] == ["OSL", "PRS"]
    assert (s.num_db, s.num_q, s.pos_radius) == (17, 0, None)  # PRS place 2 (3 images) dropped
    assert s.db_place.tolist() == [0] * 4 + [7] * 4 + [100000] * 4 + [100001] * 5
    assert s.extras["utm_zone"] == {"OSL": 32, "PRS": 31}
    assert all(Path(p).is_file() for p in s.db_paths)
    assert Path(s.db_paths[8]).name.startswith("PRS_0000000_2010_01_000_48.8566_2.3522_")
    assert s.db_heading[:2].tolist() == [0.0, 45.0]
    # images of one place lie within a few metres, places >= 100 m apart
    for pl in np.unique(s.db_place):
        u = s.db_utm[s.db_place == pl]
        assert np.linalg.norm(u - u[0], axis=1).max() < 10
    assert np.linalg.norm(s.db_utm[8] - s.db_utm[12]) > 100
    with pytest.raises(ValueError, match="no queries"):
        s.positives()
    prs = D.load(FIX / "gsv_cities", "gsv-cities", cities="PRS", min_img_per_place=5)
    assert prs.db_place.tolist() == [1] * 5
    with pytest.raises(ValueError, match=">= 6 images"):
        D.load(FIX / "gsv_cities", "gsv-cities", cities=["PRS"], min_img_per_place=6)
    with pytest.raises(FileNotFoundError, match=r"\['Rome'\]"):
        D.load(FIX / "gsv_cities", "gsv-cities", cities=["Rome"])


def test_gsv_images_root_and_index_column(tmp_path):
    root = tmp_path / "gsv"
    shutil.copytree(FIX / "gsv_cities" / "Dataframes", root / "Dataframes")
    csv_path = root / "Dataframes" / "OSL.csv"
    _rewrite_csv(csv_path, lambda ls: [("" if i == 0 else str(i - 1)) + "," + ln for i, ln in enumerate(ls)])
    with pytest.raises(FileNotFoundError, match="listed image"):
        D.load(root, "gsv-cities")
    s = D.load(root, "gsv-cities", images_root=FIX / "gsv_cities")
    assert s.num_db == 17


@pytest.mark.parametrize("edit, match", [
    (lambda ls: [ls[0].replace("lat", "latitude")] + ls[1:], r"OSL\.csv: missing column\(s\) \['lat'\]"),
    (lambda ls: [ls[0], ls[1].replace("59.9139", "nan")] + ls[2:], r"OSL\.csv: column 'lat' is NaN"),
    (lambda ls: [ls[0], ls[1].replace("2010", "2010.5", 1)] + ls[2:], r"OSL\.csv: column 'year' must hold integers"),
])
def test_gsv_malformed(tmp_path, edit, match):
    root = _copy("gsv_cities", tmp_path)
    _rewrite_csv(root / "Dataframes" / "OSL.csv", edit)
    with pytest.raises(ValueError, match=match):
        D.load(root, "gsv-cities")


def test_gsv_missing_image(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    victim = sorted((root / "Images" / "PRS").iterdir())[0]
    victim.unlink()
    with pytest.raises(FileNotFoundError, match=victim.name):
        D.load(root, "gsv-cities")


# --------------------------------------------------------------------------------------------- Nordland
def test_nordland_fixture_protocols():
    s = D.load(FIX / "nordland", "nordland")
    assert (s.num_db, s.num_q, s.pos_radius) == (40, 4, 25.0)
    assert s.extras["q_frame"].tolist() == [0, 10, 20, 30] and s.extras["query_frame_step"] == 10
    assert _pos(s) == [[0, 1], [9, 10, 11], [19, 20, 21], [29, 30, 31]]  # GSV-Cities Nordland_gt.npy style
    s25 = D.load(FIX / "nordland", "nordland", protocol="25m")
    assert _pos(s25)[1] == list(range(0, 21)) and _pos(s25)[0] == list(range(0, 11))
    s1 = D.load(FIX / "nordland", "nordland", query_frame_step=1)
    assert _pos(s1)[1] == [0, 1, 2]
    with pytest.raises(ValueError, match="protocol must be 'auto' or one of"):
        D.load(FIX / "nordland", "nordland", protocol="2frames")


def test_nordland_gmberton_and_custom_layouts(tmp_path):
    base = tmp_path / "nordland" / "images" / "test"
    for f in range(12):
        MF.write_jpeg(base / "database" / f"@0@{f * 2.38:.2f}@@@@@{f}@@@@@@@@.jpg", f)
    MF.write_jpeg(base / "queries" / "@0@11.90@@@@@5@@@@@@@@.jpg", 99)
    s = D.load(tmp_path / "nordland", "nordland", protocol="25m")
    assert s.extras["q_frame"].tolist() == [5] and sorted(_pos(s)[0]) == list(range(12))
    s1 = D.load(tmp_path / "nordland", "nordland", protocol="1frame")
    assert sorted(s1.extras["db_frame"][s1.positives()[0]].tolist()) == [4, 5, 6]
    auto = D.load(tmp_path / "nordland", "nordland")       # gmberton's folder: its own +-10 frames
    assert auto.extras["protocol"] == "25m" and sorted(_pos(auto)[0]) == list(range(12))
    raw = tmp_path / "raw"
    for f in (2, 3, 4, 7):
        MF.write_jpeg(raw / "summer" / f"image-{f:05d}.png", f)
    MF.write_jpeg(raw / "winter" / "image-00003.png", 5)
    s = D.load(raw, "nordland", db_folder="summer", q_folder="winter")
    assert s.extras["db_frame"].tolist() == [2, 3, 4, 7] and _pos(s) == [[0, 1, 2]]
    with pytest.raises(ValueError, match="both db_folder and q_folder"):
        D.load(raw, "nordland", db_folder="summer")
    MF.write_jpeg(raw / "winter" / "frame.png", 5)
    with pytest.raises(ValueError, match=r"frame\.png: no frame number"):
        D.load(raw, "nordland", db_folder="summer", q_folder="winter")
    MF.write_jpeg(base / "queries" / "@0@11.90@@@@@x@@@@@@@@.jpg", 98)
    with pytest.raises(ValueError, match=r"field 7 \(frame number\)"):
        D.load(tmp_path / "nordland", "nordland")


# --------------------------------------------------------------------------------------------- entry point
def test_load_rejects_bad_arguments():
    with pytest.raises(ValueError, match="unknown dataset format 'tokyo'"):
        D.load(FIX, "tokyo")
    with pytest.raises(ValueError, match=r"does not take option\(s\) \['cities'\]"):
        D.load(FIX / "nordland", "nordland", cities=["x"])
    with pytest.raises(ValueError, match="images_root is only used"):
        D.load(FIX / "nordland", "nordland", images_root=FIX)
    with pytest.raises(FileNotFoundError):
        D.load(FIX / "absent", "gmberton")
    with pytest.raises(ValueError, match="pos_radius must be positive"):
        D.load(FIX / "gmberton" / "pitts30k", "gmberton", pos_radius=0)


def test_geosplit_validation():
    with pytest.raises(ValueError, match="q_utm is NaN/inf for b.jpg"):
        D.GeoSplit("x", "custom", ["a.jpg"], ["b.jpg"], np.zeros((1, 2)), np.full((1, 2), np.nan), 25.0)
    with pytest.raises(ValueError, match="db_utm has 2 rows but 1 db paths"):
        D.GeoSplit("x", "custom", ["a.jpg"], [], np.zeros((2, 2)), np.zeros((0, 2)), 25.0)
    s = D.GeoSplit("x", "custom", ["a.jpg"], ["b.jpg"], np.zeros((1, 2)), np.ones((1, 2)), None)
    with pytest.raises(ValueError, match="no positives radius"):
        s.positives()
    assert _pos(s, 2.0) == [[0]]
    with pytest.raises(FileNotFoundError, match="a.jpg"):
        s.check_files()


# --------------------------------------------------------------------------------------------- UTM
def test_latlon_to_utm_matches_sfxl_geotag():
    e, n, zone = D.latlon_to_utm(37.74472, -122.50057)
    assert zone == 10
    assert abs(e - 544000.32) < 1.0 and abs(n - 4177609.18) < 1.5  # lat/lon given to 1e-5 degree
    e, n, zone = D.latlon_to_utm([-33.8688], [151.2093])
    assert zone == 56 and n[0] > 6e6  # southern hemisphere false northing
    assert D.utm_zone(60.39, 5.32) == 32 and D.utm_zone(78.2, 15.6) == 33 and D.utm_zone(0, 0) == 31
    with pytest.raises(ValueError, match="NaN"):
        D.latlon_to_utm([np.nan], [1.0])
    with pytest.raises(ValueError, match="same shape"):
        D.latlon_to_utm([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="within"):
        D.latlon_to_utm(88.0, 1.0)


# --------------------------------------------------------------------------------------------- images
def test_image_dataset_reads_resizes_normalises():
    from PIL import Image

    s = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    ds = s.image_dataset("all")
    assert len(ds) == 11
    x, i = ds[9]
    assert x.shape == (3, 12, 16) and i == 9 and x.dtype == torch.float32
    raw = torch.from_numpy(np.array(Image.open(s.q_paths[1]).convert("RGB"))).permute(2, 0, 1).float() / 255
    mean, std = torch.tensor(IMAGENET_MEAN).view(3, 1, 1), torch.tensor(IMAGENET_STD).view(3, 1, 1)
    assert torch.allclose(x, (raw - mean) / std, atol=1e-6)
    small = D.ImageDataset(s.db_paths, size=(6, 8))
    xs, _ = small[0]
    assert xs.shape == (3, 6, 8)
    assert torch.allclose(D.read_image(s.db_paths[0], normalize=False).mean(), (xs * std + mean).mean(), atol=0.02)
    batch, idx = next(iter(torch.utils.data.DataLoader(small, batch_size=4)))
    assert batch.shape == (4, 3, 6, 8) and idx.tolist() == [0, 1, 2, 3]
    assert D.ImageDataset(s.db_paths, size=5)[0][0].shape == (3, 5, 5)


def test_image_dataset_errors(tmp_path):
    with pytest.raises(ValueError, match="empty"):
        D.ImageDataset([])
    with pytest.raises(ValueError, match="sequence of image paths"):
        D.ImageDataset("a.jpg")
    with pytest.raises(ValueError, match="size must"):
        D.ImageDataset(["a.jpg"], size=(0, 4))
    with pytest.raises(FileNotFoundError, match="absent.jpg"):
        D.ImageDataset([tmp_path / "absent.jpg"])[0]
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"no jpeg here")
    with pytest.raises(ValueError, match="cannot read image .*broken.jpg"):
        D.read_image(bad)
    with pytest.raises(IndexError):
        D.ImageDataset([bad])[3]
    s = D.load(FIX / "nordland", "nordland")
    with pytest.raises(ValueError, match="which must be"):
        s.image_dataset("queries")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert s.image_dataset("db")[0][0].shape == (3, 12, 16)


# --------------------------------------------------------------------------------------------- issue 13
def test_msls_train_cities_keep_places_apart():
    s = D.load(FIX / "msls", "msls", cities="train" if False else ["trondheim", "london", "amman"], check_files=True)
    pairs = {}
    for reg, cl, pl in zip(np.concatenate([s.db_region, s.q_region]),
                           np.concatenate([s.extras["db_cluster"], s.extras["q_cluster"]]),
                           np.concatenate([s.db_place, s.q_place])):
        if cl >= 0:
            pairs.setdefault(int(pl), set()).add((str(reg), int(cl)))
    assert all(len(v) == 1 for v in pairs.values())             # one place = one (city, cluster)
    assert len(pairs) == len({next(iter(v)) for v in pairs.values()}) == 3 * 3   # clusters 1, 2, 4 per city


def test_unreadable_images_found_and_dropped():
    s = D.load(FIX / "msls", "msls", cities=["london"])
    bad = D.find_unreadable_images(s.db_paths + s.q_paths)
    assert len(bad) == 1 and "truncated" in bad[0][1].lower()
    bad_threads = D.find_unreadable_images((s.db_paths + s.q_paths) * 20, num_workers=2)
    assert len(bad_threads) == 20
    t = D.drop_images(s, [bad[0][0]])
    assert t.num_db == s.num_db - 1 and t.num_q == s.num_q and bad[0][0] not in t.db_paths
    assert len(t.extras["db_key"]) == t.num_db and len(t.db_place) == t.num_db
    assert D.drop_images(s, []) is s
    with pytest.raises(ValueError, match="sequence"):
        D.find_unreadable_images("x.jpg")
    with pytest.raises(ValueError, match="GeoSplit"):
        D.drop_images("x", [])


def test_gmberton_ignores_stray_files_as_the_benchmark(tmp_path):
    root = _copy("gmberton", tmp_path) / "pitts30k"
    db = root / "images" / "test" / "database"
    MF.write_jpeg(db / MF.gmberton_name(544000.0, 4177609.0).replace(".jpg", ".JPG"), 1)
    from PIL import Image
    Image.new("RGB", (4, 4)).save(db / "thumbnail.png")
    with pytest.warns(UserWarning, match=r"2 image file\(s\) not named \*\.jpg are ignored"):
        s = D.load(root, "gmberton")
    assert s.num_db == 6


def test_recall_conventions_per_format():
    assert D.recall_convention("msls") == "exclude"
    assert {D.recall_convention(f) for f in ("pitts", "gmberton", "gsv-cities", "nordland")} == {"all"}
    with pytest.raises(ValueError, match="unknown dataset format"):
        D.recall_convention("tokyo")
    split = D.TrainingSplit(D.load(FIX / "gmberton" / "pitts30k", "gmberton"), (8, 8))
    assert split.recall_convention == "all"


# --------------------------------------------------------------------------------------------- package layout
def test_registry_is_the_one_list_of_formats():
    import vpr_nb.datasets as pkg

    assert D.FORMATS == tuple(D.REGISTRY) == ("pitts", "gmberton", "msls", "gsv-cities", "nordland")
    for name, spec in D.REGISTRY.items():
        assert spec.name == name and spec.recall == D.recall_convention(name)
        module = importlib.import_module(spec.loader.__module__)       # one module per format ...
        assert module.__name__.startswith("vpr_nb.datasets.") and f'"{name}"' in module.__doc__
        assert getattr(pkg, spec.loader.__name__) is spec.loader       # ... whose loader the package exports
    assert D.REGISTRY["pitts"].options == ["images_root"]
    assert D.REGISTRY["gsv-cities"].options == ["cities", "min_img_per_place", "images_root"]
    assert D.FORMAT_RECALL["synthetic"] == "exclude" and set(D.FORMAT_RECALL) == set(D.FORMATS) | {"synthetic"}
    with pytest.raises(ValueError, match="images_root is only used by the 'pitts' and 'gsv-cities' formats"):
        D.load(FIX / "nordland", "nordland", images_root=FIX)


def test_dataset_format_validates_its_loader():
    def good(root, *, size=1, check_files=True):
        return root

    assert D.DatasetFormat("toy", good, recall="all").options == ["size"]
    with pytest.raises(ValueError, match="recall must be one of"):
        D.DatasetFormat("toy", good, recall="some")
    with pytest.raises(ValueError, match="must take check_files"):
        D.DatasetFormat("toy", lambda root: root, recall="all")
    with pytest.raises(ValueError, match="first parameter must be the dataset location"):
        D.DatasetFormat("toy", lambda *, check_files=True: None, recall="all")
    with pytest.raises(ValueError, match="non-empty name"):
        D.DatasetFormat("", good, recall="all")
    with pytest.raises(ValueError, match="must take \\['check_files'\\]"):
        D.DatasetFormat("toy", good, recall="all", load_part=lambda root, part: root)


def test_each_format_line_holds_what_the_commands_read(recwarn):
    """load_part reads one part of a dataset folder; the line says which part validates and which tests."""
    R = D.REGISTRY
    assert [f.name for f in R.values() if f.own_val] == ["pitts", "gmberton"]       # msls-val is MSLS's test set
    assert (R["msls"].val_part, R["msls"].test_part, R["gsv-cities"].test_part, R["nordland"].train) == \
        ("val", "val", None, False)
    assert [f.name for f in R.values() if f.places] == ["msls", "gsv-cities"]
    assert [f.name for f in R.values() if not f.queries] == ["gsv-cities"]
    assert R["pitts"].settings == {"pitts_set": ("pitts30k", "pitts250k")}
    parts = {("pitts", "val"): FIX / "pitts", ("gmberton", "test"): FIX / "gmberton" / "pitts30k",
             ("msls", "val"): FIX / "msls_val_only", ("msls", "train"): FIX / "msls",
             ("gsv-cities", "train"): FIX / "gsv_cities", ("nordland", "test"): FIX / "nordland"}
    for (name, part), root in parts.items():
        geo = R[name].load_part(root, part, check_files=False)
        assert isinstance(geo, D.GeoSplit) and geo.format == name and geo.num_db > 0, (name, part)
    assert D.REGISTRY["pitts"].load_part(FIX / "pitts", "test").extras["dataset"] == "pitts30k"
    with pytest.raises(ValueError, match="must take \\['nordland_protocol'\\]"):     # load_nordland calls it protocol
        D.DatasetFormat("toy", D.load_nordland, recall="all", load_part=D.load_nordland,
                        settings={"nordland_protocol": None})
    with pytest.raises(ValueError, match="already registered"):
        D.register(R["pitts"])
    with pytest.raises(ValueError, match="other than 'synthetic'"):
        D.DatasetFormat("synthetic", D.load_nordland, recall="all")


def test_a_training_split_is_a_split_with_lazy_images():
    from vpr_nb.split import Split

    t = D.TrainingSplit(D.load(FIX / "msls", "msls", cities=["trondheim", "london", "amman"]), (8, 8))
    assert isinstance(t, Split) and t.has_places and t.has_queries and t.image_names("q") == t.geo.q_paths
    pool = t.place_pool()
    keep = np.concatenate([t.db_place, t.q_place]) >= 0
    assert isinstance(pool.images, D.ImageArray) and pool.images.paths == list(np.array(t.db_paths + t.q_paths)[keep])
    assert (pool.places >= 0).all() and len(pool.places) == len(pool.utm) == len(pool.regions) == keep.sum()
    gsv = D.TrainingSplit(D.load(FIX / "gsv_cities", "gsv-cities"), (8, 8))
    assert gsv.q_images is None and not gsv.has_queries and len(gsv.place_pool().images) == gsv.geo.num_db
    gm = D.TrainingSplit(D.load(FIX / "gmberton" / "pitts30k", "gmberton"), (8, 8))
    with pytest.raises(ValueError, match="has no place ids"):
        gm.place_pool()


def test_one_region_aware_positives_for_every_split():
    from vpr_nb.evaluation import positives_within

    s = D.load(FIX / "msls", "msls", cities=["trondheim", "london", "amman"])
    per_city = D.region_positives(s.db_utm, s.q_utm, 25.0, s.db_region, s.q_region, name=s.name)
    assert _pos(s) == [p.tolist() for p in per_city]
    for q, hits in enumerate(per_city):                              # never across cities
        assert all(s.db_region[j] == s.q_region[q] for j in hits)
    t = D.TrainingSplit(s, (8, 8))
    assert [p.tolist() for p in t.positives()] == _pos(s) and [p.tolist() for p in t.positives(5.0)] == _pos(s, 5.0)
    flat = D.region_positives(s.db_utm, s.q_utm, 25.0)              # without regions: the plain radius search
    assert [p.tolist() for p in flat] == [p.tolist() for p in positives_within(s.db_utm, s.q_utm, 25.0)]
    with pytest.raises(ValueError, match="gsv-cities has no queries"):
        D.TrainingSplit(D.load(FIX / "gsv_cities", "gsv-cities"), (8, 8)).positives()
    with pytest.raises(ValueError, match="one region per image"):
        D.region_positives(s.db_utm, s.q_utm, 25.0, s.db_region[:1], s.q_region)
    with pytest.raises(ValueError, match="geo must be a GeoSplit"):
        D.TrainingSplit("x", (8, 8))


def test_one_imagenet_normalisation_path():
    from vpr_nb.image_tensors import images_to_tensor, normalize_imagenet

    s = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    raw = D.read_image(s.db_paths[0], (6, 8), normalize=False)
    assert torch.equal(D.read_image(s.db_paths[0], (6, 8)), normalize_imagenet(raw))
    u8 = D.ImageArray(s.db_paths[:2], (6, 8))[:]
    assert torch.equal(images_to_tensor(u8), normalize_imagenet(torch.from_numpy(u8).permute(0, 3, 1, 2).float() / 255))
    with pytest.raises(ValueError, match="float tensor with 3 channels"):
        normalize_imagenet(torch.zeros(2, 4, 4, 3))
    with pytest.raises(ValueError, match="scale uint8 images"):
        normalize_imagenet(torch.zeros(3, 4, 4, dtype=torch.uint8))


def test_public_names_and_wheel_packaging():
    old_api = ["FORMATS", "GeoSplit", "ImageDataset", "read_image", "load", "load_pitts", "load_gmberton", "load_msls",
               "load_gsv_cities", "load_nordland", "latlon_to_utm", "utm_zone", "parse_gmberton_name", "gsv_image_name",
               "ImageArray", "TrainingSplit", "RECALL_CONVENTIONS", "FORMAT_RECALL", "recall_convention",
               "find_unreadable_images", "drop_images", "MSLS_CITIES", "NORDLAND_PROTOCOLS", "IMAGE_SUFFIXES"]
    assert set(old_api) <= set(D.__all__) and all(hasattr(D, n) for n in D.__all__)
    from setuptools import find_packages     # what setup.py discovers (pyproject.toml holds no explicit list)
    assert "vpr_nb.datasets" in find_packages(str(FIX.parent), include=["vpr_nb", "vpr_nb.*"]), "a wheel would ship without the package"
