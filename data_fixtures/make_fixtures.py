"""Create the tiny dataset fixtures of ``data_fixtures/``, one per real format read by ``vpr_nb.datasets``.

Run from the repository root (deterministic: same bytes every run with the same numpy/scipy/Pillow)::

    .venv/bin/python data_fixtures/make_fixtures.py

Every fixture mimics the real on-disk format (folder layout, file names, CSV headers, ``.mat`` struct
layout) with a handful of 16x12 JPEGs; the geometry is chosen so that the tests know the answer
(which queries have which positives). Layouts:

- ``pitts/``      ``datasets/pitts30k_{train,val,test}.mat`` (NetVLAD dbStruct), ``000/*.jpg``, ``queries_real/000/*.jpg``
- ``gmberton/``   ``pitts30k/images/test/{database,queries}/@east@north@zone@...@.jpg``
- ``msls/``       ``train_val/{cph,sf,trondheim,london,amman}/{database,query}/{images/*.jpg,raw.csv,
                  postprocessed.csv,seq_info.csv,subtask_index.csv}``; one london database JPEG is truncated
- ``msls_val_only/`` the same files for cph and sf only (an MSLS folder holding only the val cities)
- ``gsv_cities/`` ``Dataframes/{PRS,OSL}.csv``, ``Images/{PRS,OSL}/*.jpg``
- ``nordland/``   ``ref/0000000.jpg`` ... (40 summer frames), ``query/0000000.jpg`` ... (4 winter frames = frames 0, 10, 20, 30)

The helpers (``write_jpeg``, ``write_pitts_mat``, ``write_csv``) are also imported by the tests to build
malformed variants.
"""
from __future__ import annotations

import io
import math
import shutil
import string
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
IMG_W, IMG_H = 16, 12
_MAT_HEADER = b"MATLAB 5.0 MAT-file, written by vpr-notebooks data_fixtures/make_fixtures.py"


def write_jpeg(path: Path, seed: int) -> None:
    """A deterministic 16x12 RGB JPEG (a colour gradient, different for every seed)."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    c0, c1 = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
    t = np.linspace(0.0, 1.0, IMG_W)[None, :, None]
    img = (c0 * (1 - t) + c1 * t).repeat(IMG_H, axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img.astype(np.uint8), "RGB").save(path, format="JPEG", quality=75)


def write_csv(path: Path, header: list[str], rows: list[list], index: bool = True) -> None:
    """Write a CSV as pandas ``to_csv`` does (``index=True``: a leading unnamed index column)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(([""] if index else []) + header)]
    for i, row in enumerate(rows):
        lines.append(",".join(([str(i)] if index else []) + [str(v) for v in row]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _cell(names: list[str]) -> np.ndarray:
    arr = np.empty((len(names), 1), dtype=object)
    for i, n in enumerate(names):
        arr[i, 0] = n
    return arr


def write_pitts_mat(path: Path, fields: dict) -> None:
    """Save ``{'dbStruct': fields}`` as a MATLAB v5 .mat (fields in the given order) with a fixed header,
    so that the bytes do not depend on the date. List-of-str values become cell arrays (N x 1)."""
    from scipy.io import savemat

    st = {k: (_cell(v) if isinstance(v, list) else v) for k, v in fields.items()}
    buf = io.BytesIO()
    savemat(buf, {"dbStruct": st}, format="5", oned_as="column")
    data = bytearray(buf.getvalue())
    data[:116] = _MAT_HEADER.ljust(116, b" ")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(data))


def pitts_fields(db_names, db_utm, q_names, q_utm, which="test") -> dict:
    """The NetVLAD dbStruct fields in Relja's order (dbBase.m), with the 25 m / 10 m thresholds."""
    return {"whichSet": which, "dbImageFns": list(db_names), "utmDb": np.asarray(db_utm, float).T,
            "qImageFns": list(q_names), "utmQ": np.asarray(q_utm, float).T,
            "numImages": float(len(db_names)), "numQueries": float(len(q_names)),
            "posDistThr": 25.0, "posDistSqThr": 625.0, "nonTrivPosDistSqThr": 100.0}


# --- Pittsburgh -------------------------------------------------------------------------------
PITTS_ORIGIN = (584000.0, 4477000.0)
PITTS_PLACES = [(0.0, 0.0), (15.0, 0.0), (60.0, 0.0), (200.0, 0.0)]  # panorama centres (E, N offsets)
PITTS_QUERIES = [(5.0, 0.0), (60.0, 20.0), (200.0, -8.0)]


def make_pitts(out: Path) -> None:
    db_names, db_utm = [], []
    seed = 0
    for p, (de, dn) in enumerate(PITTS_PLACES):
        for yaw in (1, 2):  # 2 of the 24 crops of each panorama, all with the same UTM
            name = f"000/{p * 24:06d}_pitch1_yaw{yaw}.jpg"
            db_names.append(name)
            db_utm.append((PITTS_ORIGIN[0] + de, PITTS_ORIGIN[1] + dn))
            write_jpeg(out / name, seed)
            seed += 1
    q_names, q_utm = [], []
    for i, (de, dn) in enumerate(PITTS_QUERIES):
        name = f"000/{i * 24 + 5:06d}_pitch1_yaw1.jpg"
        q_names.append(name)
        q_utm.append((PITTS_ORIGIN[0] + de, PITTS_ORIGIN[1] + dn))
        write_jpeg(out / "queries_real" / name, 100 + i)
    write_pitts_mat(out / "datasets" / "pitts30k_test.mat", pitts_fields(db_names, db_utm, q_names, q_utm))
    # train and val structs over the same images (val: the first two queries, so val != test)
    write_pitts_mat(out / "datasets" / "pitts30k_train.mat",
                    pitts_fields(db_names, db_utm, q_names, q_utm, which="train"))
    write_pitts_mat(out / "datasets" / "pitts30k_val.mat",
                    pitts_fields(db_names, db_utm, q_names[:2], q_utm[:2], which="val"))


# --- gmberton ---------------------------------------------------------------------------------
SF_ORIGIN = (544000.32, 4177609.18, 37.74472, -122.50057)  # a real SF-XL geotag


def gmberton_name(east: float, north: float, heading: int | None = None, pano: str = "", note: str = "",
                  zone: int = 10, letter: str = "S", lat: float | None = None, lon: float | None = None) -> str:
    """``@east@north@zone@letter@lat@lon@pano@tile@heading@pitch@roll@height@timestamp@note@.jpg``."""
    if lat is None:
        lat = SF_ORIGIN[2] + (north - SF_ORIGIN[1]) / 111320.0
        lon = SF_ORIGIN[3] + (east - SF_ORIGIN[0]) / (111320.0 * math.cos(math.radians(SF_ORIGIN[2])))
    h = "" if heading is None else f"{heading:03d}"
    return (f"@{east:010.2f}@{north:010.2f}@{zone:02d}@{letter}@{lat:09.5f}@{lon:010.5f}@{pano}@@{h}@@@@@{note}@.jpg")


GM_DB = [(0.0, 0.0), (20.0, 0.0), (40.0, 0.0), (100.0, 0.0), (100.0, 30.0), (300.0, 0.0)]
GM_Q = [(10.0, 0.0), (100.0, 10.0), (500.0, 0.0)]


def make_gmberton(out: Path) -> None:
    base = out / "pitts30k" / "images" / "test"
    for i, (de, dn) in enumerate(GM_DB):
        write_jpeg(base / "database" / gmberton_name(SF_ORIGIN[0] + de, SF_ORIGIN[1] + dn, 30 * i, f"pano{i}"), 200 + i)
    for i, (de, dn) in enumerate(GM_Q):
        write_jpeg(base / "queries" / gmberton_name(SF_ORIGIN[0] + de, SF_ORIGIN[1] + dn, 90, f"q{i}"), 300 + i)


# --- MSLS -------------------------------------------------------------------------------------
MSLS_CITY_ORIGINS = {  # (easting, northing, lon, lat): rough real positions
    "cph": (724000.0, 6176000.0, 12.568, 55.676),
    "sf": (551000.0, 4181000.0, -122.419, 37.775),
    "trondheim": (569000.0, 7034000.0, 10.395, 63.430),
    "london": (699000.0, 5710000.0, -0.128, 51.507),
    "amman": (775000.0, 3537000.0, 35.930, 31.950),
}
# one extra database image of london (cluster 2) whose JPEG is cut in half: a truncated file
MSLS_TRUNCATED_CITY = "london"
MSLS_TRUNCATED = (201, 2, 2, False)
# database: (E, N offset, unique_cluster ("" = none), pano); clusters group images of one place
MSLS_DB = [(0, 0, 1, False), (5, 0, 1, False), (200, 0, 2, False), (205, 3, 2, False), (400, 0, "", False),
           (600, 0, 3, True)]
# queries: (E, N offset, unique_cluster, pano, in subtask "all")
MSLS_Q = [(3, 2, 1, False, True), (210, 0, 2, False, True), (0, 5, 1, True, True), (202, 1, 2, False, False),
          (1000, 0, 4, False, True)]


def _msls_key(rng: np.random.Generator) -> str:
    alphabet = np.array(list(string.ascii_letters + string.digits + "_-"))
    return "".join(rng.choice(alphabet, 22))


def make_msls(out: Path, cities=None) -> None:
    """``cities``: the city folders to write (default all; ``("cph", "sf")`` gives a val-only MSLS folder)."""
    rng = np.random.default_rng(7)
    seed = 400
    for city, (e0, n0, lon0, lat0) in MSLS_CITY_ORIGINS.items():
        if cities is not None and city not in cities:
            continue
        for side, items in (("database", MSLS_DB), ("query", MSLS_Q)):
            truncated = side == "database" and city == MSLS_TRUNCATED_CITY
            if truncated:
                items = list(items) + [MSLS_TRUNCATED]
            folder = out / "train_val" / city / side
            raw, post, seq, sub = [], [], [], []
            for j, it in enumerate(items):
                de, dn, cluster, pano = it[:4]
                in_all = it[4] if len(it) > 4 else True
                key = _msls_key(rng)
                night = j == 1
                view = ("Forward", "Backward", "Sideways")[j % 3]
                raw.append([key, f"{lon0 + de / 70000:.6f}", f"{lat0 + dn / 111320:.6f}", f"{(37.5 * j) % 360:.3f}",
                            1440000000000 + 86400000 * j, pano])
                post.append([key, f"{e0 + de:.3f}", f"{n0 + dn:.3f}", cluster, False, night, view])
                seq.append([key, f"seq{city}{side[0]}{j // 3}", j % 3])
                sub.append([in_all, j % 2 == 0, j % 2 == 1, False, night, False, False])
                write_jpeg(folder / "images" / f"{key}.jpg", seed)
                if truncated and j == len(items) - 1:
                    data = (folder / "images" / f"{key}.jpg").read_bytes()
                    (folder / "images" / f"{key}.jpg").write_bytes(data[:len(data) // 2])
                seed += 1
            write_csv(folder / "raw.csv", ["key", "lon", "lat", "ca", "captured_at", "pano"], raw)
            write_csv(folder / "postprocessed.csv", ["key", "easting", "northing", "unique_cluster", "control_panel",
                                                     "night", "view_direction"], post)
            write_csv(folder / "seq_info.csv", ["key", "sequence_key", "frame_number"], seq)
            write_csv(folder / "subtask_index.csv", ["all", "summer2winter", "winter2summer", "day2night",
                                                     "night2day", "old2new", "new2old"], sub)


# --- GSV-Cities -------------------------------------------------------------------------------
GSV_CITIES = {  # city_id: (lat, lon, {place_id: number of images}); places < 4 images are dropped by the loader
    "PRS": (48.8566, 2.3522, {0: 4, 1: 5, 2: 3}),
    "OSL": (59.9139, 10.7522, {0: 4, 7: 4}),
}


def make_gsv(out: Path) -> None:
    rng = np.random.default_rng(11)
    seed = 600
    for city, (lat0, lon0, places) in GSV_CITIES.items():
        rows = []
        for k, (pid, count) in enumerate(places.items()):
            lat = round(lat0 + 0.002 * k, 6)  # places >= 100 m apart
            lon = round(lon0 + 0.001 * k, 6)
            for j in range(count):
                year, month, northdeg = 2010 + j, 1 + (3 * j) % 12, (45 * j + 10 * k) % 360
                la, lo = round(lat + 1e-5 * j, 6), round(lon - 1e-5 * j, 6)
                panoid = _msls_key(rng)
                rows.append([pid, year, month, northdeg, city, la, lo, panoid])
                # GSVCitiesDataset.get_img_name: city_id, place zfill(7), year, month zfill(2), northdeg zfill(3), lat, lon, panoid
                name = f"{city}_{pid:07d}_{year}_{month:02d}_{northdeg:03d}_{la}_{lo}_{panoid}.jpg"
                write_jpeg(out / "Images" / city / name, seed)
                seed += 1
        write_csv(out / "Dataframes" / f"{city}.csv",
                  ["place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid"], rows, index=False)


# --- Nordland (VPR-Bench / GSV-Cities layout) --------------------------------------------------
NORDLAND_REFS, NORDLAND_QUERIES = 40, 4


def make_nordland(out: Path) -> None:
    for f in range(NORDLAND_REFS):
        write_jpeg(out / "ref" / f"{f:07d}.jpg", 800 + f)
    for i in range(NORDLAND_QUERIES):
        write_jpeg(out / "query" / f"{i:07d}.jpg", 900 + i)


def main(root: Path = HERE) -> None:
    for name, fn in (("pitts", make_pitts), ("gmberton", make_gmberton), ("msls", make_msls),
                     ("msls_val_only", lambda o: make_msls(o, ("cph", "sf"))),
                     ("gsv_cities", make_gsv), ("nordland", make_nordland)):
        out = root / name
        if out.exists():
            shutil.rmtree(out)
        fn(out)
    total = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    print(f"fixtures written under {root}: {total / 1024:.1f} KiB in total")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE)
