"""A dataset format defined in this file alone trains and evaluates through the reproduction commands.

The toy format is one loader, one ``load_part`` and one :class:`vpr_nb.datasets.DatasetFormat` line,
registered from here: no other module knows it. Its two cities share their UTM coordinates and their
database images (each place of city B looks exactly like the place of city A at the same spot), so only the
region labels keep them apart: ``train`` and ``evaluate`` must report the same Recall@N, and no positive may
cross a city.
"""
import csv
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vpr_nb import config as C
from vpr_nb import datasets as D
from vpr_nb import experiment as E
from vpr_nb.evaluate import main as evaluate_main
from vpr_nb.evaluation import compute_descriptors, recall_at_n, retrieve
from vpr_nb.split import positives_within
from vpr_nb.train import main as train_main
from vpr_nb.training import load_checkpoint

CITIES = ("alpha", "beta")


def load_toy(folder, *, check_files: bool = True) -> D.GeoSplit:
    """``folder/images.csv`` (side, path, east, north, city) as a GeoSplit; positives within 25 m per city."""
    folder = Path(folder)
    with open(folder / "images.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    side = {s: [r for r in rows if r["side"] == s] for s in ("db", "q")}
    kw = {}
    for s, rs in side.items():
        kw[f"{s}_paths"] = [str(folder / r["path"]) for r in rs]
        kw[f"{s}_utm"] = np.array([[float(r["east"]), float(r["north"])] for r in rs])
        kw[f"{s}_region"] = np.array([r["city"] for r in rs])
    split = D.GeoSplit(name=f"toy-{folder.name}", format="toy-cities", pos_radius=25.0, train_pos_radius=10.0, **kw)
    if check_files:
        split.check_files()
    return split


def load_part(root, part: str, *, check_files: bool = True) -> D.GeoSplit:
    return load_toy(Path(root) / part, check_files=check_files)


TOY = D.DatasetFormat("toy-cities", load_toy, recall="all", load_part=load_part)


@pytest.fixture
def toy_format():
    fmt = D.register(TOY)
    yield fmt
    D.REGISTRY.pop(fmt.name)


def write_toy(root: Path, places: int = 10, seed: int = 0) -> Path:
    """Parts train / val / test of two cities at the same coordinates (places 40 m apart), one database
    image per place (the same pixels in both cities) and one query 3 m away (its own noise)."""
    rng = np.random.default_rng(seed)
    for p, part in enumerate(("train", "val", "test")):
        folder = root / part
        folder.mkdir(parents=True)
        looks = rng.integers(0, 256, (places, 4, 4, 3))
        rows = []
        for c, city in enumerate(CITIES):
            for i in range(places):
                east, north = 40.0 * i, 1000.0 * p
                db = np.kron(looks[i], np.ones((4, 4, 1))).astype(np.uint8)
                q = np.clip(db + rng.normal(0, 25, db.shape), 0, 255).astype(np.uint8)
                for s, img, de in (("db", db, 0.0), ("q", q, 3.0)):
                    name = f"{s}_{city}_{i}.png"
                    Image.fromarray(img).save(folder / name)
                    rows.append({"side": s, "path": name, "east": east + de, "north": north, "city": city})
        with open(folder / "images.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return root


def test_a_format_registered_here_trains_and_evaluates_through_the_commands(toy_format, tmp_path):
    root = write_toy(tmp_path / "toy")
    sets = ["data.format=toy-cities", f"data.root={root}", "data.image_size=[16,16]", "data.image_check_workers=1",
            'model.backbone_kwargs={"width": 8, "out_channels": 16}', "source.max_heading_diff=none",
            "source.batch_size=4", "source.num_negatives=2", "source.num_candidates=8", "train.epochs=1"]
    args = [a for s in sets for a in ("--set", s)]
    run = tmp_path / "run"
    assert train_main(["--preset", "synthetic-city-triplet", "--out", str(run), "--no-progress"] + args) == 0
    trained = json.loads((run / "results.json").read_text())
    assert trained["test_data"].startswith("toy-cities:test") and trained["val"].startswith("toy-cities:val")
    assert trained["recall_convention"] == "all"
    assert evaluate_main(["--run", str(run), "--out", str(tmp_path / "ev")]) == 0
    evaluated = json.loads((tmp_path / "ev" / "recalls.json").read_text())
    assert evaluated["num_queries"] == 2 * 10 and evaluated["recall_convention"] == "all"
    assert {n: evaluated["recall"][n] for n in trained["test"]} == trained["test"]     # the same Recall@N

    # positives stay inside a city, although the cities' geotags coincide
    cfg = C.resolve("synthetic-city-triplet", sets)
    test = E.load_split(cfg, "test")
    pos = test.positives()
    assert all((test.db_region[p] == test.q_region[q]).all() and len(p) == 1 for q, p in enumerate(pos))
    flat = positives_within(test.db_utm, test.q_utm, test.pos_radius)
    assert all(len(p) == 2 for p in flat)                         # by geotags alone: the other city's twin too
    # both commands counted a hit only on the query's own city: with the twins as positives it would be more
    model = E.build(cfg)
    model.load_state_dict(load_checkpoint(run / "checkpoints" / "best.pt")["model"])
    _, idx = retrieve(compute_descriptors(model, test.db_images), compute_descriptors(model, test.q_images), 10)
    assert recall_at_n(idx, pos, (1, 5, 10), "all") == {int(n): v for n, v in trained["test"].items()}
    assert recall_at_n(idx, flat, (1,), "all")[1] > trained["test"]["1"]
