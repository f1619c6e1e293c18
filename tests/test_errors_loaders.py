"""Wrong dataset inputs end in a clear error, a warning naming the city / file, or a correct result.

Each test copies a tiny fixture of data_fixtures/ into tmp_path and breaks it one way.
"""
import shutil
from pathlib import Path

import numpy as np
import pytest

from dataset_fixtures import FIX, MF
from dataset_fixtures import copy_fixture as _copy
from dataset_fixtures import edit_lines as _edit
from vpr_nb import datasets as D



def _header_only(folder):
    for name in ("raw.csv", "postprocessed.csv"):
        _edit(folder / name, lambda ls: ls[:1])


# --------------------------------------------------------------------------------------------- MSLS
def test_msls_city_with_header_only_query_csvs_is_named(tmp_path):
    root = _copy("msls", tmp_path)
    _header_only(root / "train_val" / "sf" / "query")
    with pytest.warns(UserWarning, match=r"MSLS city 'sf' has no usable queries \(query/postprocessed\.csv lists no image\)"):
        s = D.load(root, "msls")
    assert "sf" not in set(s.q_region) and "sf" in set(s.db_region)


def test_msls_city_of_panoramas_only_is_named(tmp_path):
    root = _copy("msls", tmp_path)
    _edit(root / "train_val" / "cph" / "query" / "raw.csv", lambda ls: [ls[0]] + [ln.replace("False", "True") for ln in ls[1:]])
    with pytest.warns(UserWarning, match=r"MSLS city 'cph' has no usable queries \(all 5 query images are panoramas"):
        s = D.load(root, "msls", cities="val")
    assert set(s.q_region) == {"sf"}
    assert D.load(root, "msls", cities="val", exclude_panos=False).num_q == 10   # kept when asked


def test_msls_without_any_query_or_database_image_raises(tmp_path):
    root = _copy("msls", tmp_path)
    for city in ("cph", "sf"):
        _header_only(root / "train_val" / city / "query")
    with pytest.raises(ValueError, match=r"no usable query image in any of the cities \(cph: query/postprocessed"):
        D.load(root, "msls", cities="val")
    for city in ("cph", "sf"):
        _header_only(root / "train_val" / city / "database")
    with pytest.raises(ValueError, match=r"no usable database image in any of the cities"):
        D.load(root, "msls", cities="val")


def test_msls_latin1_csv_names_the_file_and_the_fix(tmp_path):
    root = _copy("msls", tmp_path)
    raw = root / "train_val" / "sf" / "database" / "raw.csv"
    lines = raw.read_text().splitlines()
    lines[3] += ",S\u00e3o Paulo"                     # an exported note column, written in latin-1
    raw.write_bytes(("\n".join(lines) + "\n").encode("latin-1"))
    with pytest.raises(ValueError, match=r"sf/database/raw\.csv, line 4: byte 0xe3 .* not UTF-8.*iconv -f latin1"):
        D.load(root, "msls")


def test_msls_duplicated_query_key_names_file_and_rows(tmp_path):
    root = _copy("msls", tmp_path)
    for name in ("raw.csv", "postprocessed.csv"):
        _edit(root / "train_val" / "cph" / "query" / name, lambda ls: ls + [ls[2]])
    with pytest.raises(ValueError, match=r"cph/query/postprocessed\.csv: 1 key\(s\) are listed more than once, "
                                         r"e\.g\. '\S+' in data rows \[2, 6\]"):
        D.load(root, "msls")


# --------------------------------------------------------------------------------------------- Nordland
def test_nordland_count_mismatch_raises_with_counts_and_folders(tmp_path):
    root = _copy("nordland", tmp_path)
    for p in sorted((root / "ref").iterdir())[20:]:
        p.unlink()
    with pytest.raises(ValueError, match=r"nordland/query and \S+nordland/ref do not match: 1 of 4 queries .*frame 30.*"
                                         r"among the 20 references \(frames 0\.\.19\).*query_frame_step=10"):
        D.load(root, "nordland")


def test_nordland_repeated_query_frame_raises(tmp_path):
    root = _copy("nordland", tmp_path)
    shutil.copy(root / "query" / "0000001.jpg", root / "query" / "image-1.jpg")
    with pytest.raises(ValueError, match=r"nordland/query: 1 image\(s\) repeat the frame number of another"):
        D.load(root, "nordland")


# --------------------------------------------------------------------------------------------- GSV-Cities
def test_gsv_repeated_row_is_counted_once_with_a_warning(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    _edit(root / "Dataframes" / "OSL.csv", lambda ls: ls + [ls[3]])
    with pytest.warns(UserWarning, match=r"OSL\.csv: 1 row\(s\) repeat an earlier row \(the same image\), "
                                         r"e\.g\. data rows \[3, 9\]"):
        s = D.load(root, "gsv-cities")
    ref = D.load(FIX / "gsv_cities", "gsv-cities")
    assert [Path(p).name for p in s.db_paths] == [Path(p).name for p in ref.db_paths]
    assert s.db_place.tolist() == ref.db_place.tolist()


def test_gsv_latitude_out_of_range_names_file_and_row(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    _edit(root / "Dataframes" / "PRS.csv", lambda ls: ls[:2] + [ls[2].replace("48.85", "94.85", 1)] + ls[3:])
    with pytest.raises(ValueError, match=r"PRS\.csv: column 'lat', data row 2 \(line 3\): 94\.85\S* is outside \[-84, 84\]"):
        D.load(root, "gsv-cities")


def test_gsv_city_that_drops_out_is_named(tmp_path):
    root = _copy("gsv_cities", tmp_path)
    _edit(root / "Dataframes" / "OSL.csv", lambda ls: ls[:1])
    with pytest.warns(UserWarning, match=r"OSL\.csv: lists no image \(header only\); GSV-Cities city 'OSL' is left out"):
        s = D.load(root, "gsv-cities")
    assert set(s.db_region) == {"PRS"}
    with pytest.raises(ValueError, match=r"no place of cities \['OSL'\].*OSL\.csv: lists no image"):
        D.load(root, "gsv-cities", cities=["OSL"])


# --------------------------------------------------------------------------------------------- Pittsburgh
def _pitts_mat(tmp_path, db_names, db_utm, q_names, q_utm):
    root = _copy("pitts", tmp_path)
    path = root / "datasets" / "bad_pitts30k_test.mat"
    MF.write_pitts_mat(path, MF.pitts_fields(db_names, db_utm, q_names, q_utm))
    return path


def test_pitts_empty_or_duplicated_lists_are_refused(tmp_path):
    s = D.load(FIX / "pitts" / "datasets" / "pitts30k_test.mat", "pitts")
    db = [str(Path(p).relative_to(FIX / "pitts")) for p in s.db_paths]
    q = [str(Path(p).relative_to(FIX / "pitts" / "queries_real")) for p in s.q_paths]
    path = _pitts_mat(tmp_path / "a", db, s.db_utm, [], np.zeros((0, 2)))
    with pytest.raises(ValueError, match=r"bad_pitts30k_test\.mat: dbStruct field 3 \(qImageFns\) lists no image"):
        D.load(path, "pitts")
    path = _pitts_mat(tmp_path / "b", db[:-1] + db[:1], s.db_utm, q, s.q_utm)
    with pytest.raises(ValueError, match=r"field 1 \(dbImageFns\) lists 1 image\(s\) more than once, .* entries \[0, 7\]"):
        D.load(path, "pitts")


def test_an_empty_database_is_refused_when_the_split_is_made():
    with pytest.raises(ValueError, match="toy: the database is empty"):
        D.GeoSplit(name="toy", format="gmberton", db_paths=[], q_paths=["q.jpg"], db_utm=np.zeros((0, 2)),
                   q_utm=np.zeros((1, 2)), pos_radius=25.0)


def test_latlon_to_utm_names_the_bad_position():
    with pytest.raises(ValueError, match=r"1 position\(s\) are not, first at flat index 2: lat=95, lon=10"):
        D.latlon_to_utm([45.0, 46.0, 95.0], [10.0, 10.0, 10.0])
