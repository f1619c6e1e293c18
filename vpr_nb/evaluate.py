"""Evaluate a trained checkpoint: ``python -m vpr_nb.evaluate --run DIR [--set data.KEY=VALUE ...] --out DIR``.

``--run`` is an output folder of ``python -m vpr_nb.train`` (its ``config.json`` rebuilds the model,
``checkpoints/best.pt`` holds the weights); alternatively ``--preset NAME --checkpoint FILE``.
The dataset is the run's ``data`` section, changed with ``--set data.format=gmberton --set
data.root=/path`` to evaluate on another dataset. Writes ``recalls.json`` (Recall@1/5/10/20 on the
test split), optionally ``predictions.csv`` (``--predictions``: query, then the top-k database images)
and ``retrieval_grid.png`` (the first queries with their top-5, green = correct, red = wrong).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from .evaluation import as_image_array, compute_descriptors, positives_within, recall_at_n, retrieve
from .models import build_model
from .train import load_data, resolve_config
from .training import load_checkpoint, resolve_device


def _names(split, side: str) -> list[str]:
    geo = getattr(split, "geo", None)
    if geo is not None:
        return [str(p) for p in getattr(geo, f"{side}_paths")]
    return [f"{side}_{i}" for i in range(len(getattr(split, f"{side}_utm")))]


def evaluate_checkpoint(cfg: dict, checkpoint, out: Path | None = None, ns=(1, 5, 10, 20), k: int = 20,
                        predictions: bool = False, grid_queries: int = 8, device: str = "auto") -> dict:
    """Recall@N of the weights in ``checkpoint`` (a ``{"model": state_dict}`` file) on ``cfg['data']``'s test split."""
    state = load_checkpoint(checkpoint)
    if "model" not in state:
        raise ValueError(f"{checkpoint} has no 'model' entry; pass a best.pt/last.pt written by vpr_nb.training")
    m = cfg["model"]
    model = build_model(m["backbone"], m["aggregator"], backbone_kwargs=m["backbone_kwargs"] or None,
                        **m["aggregator_kwargs"])
    model.load_state_dict(state["model"])
    model.to(resolve_device(device))
    _, _, test = load_data(cfg["data"], splits=("test",))
    db = compute_descriptors(model, test.db_images)
    q = compute_descriptors(model, test.q_images)
    k = min(k, len(db))
    _, idx = retrieve(db, q, k)
    pos = positives_within(test.db_utm, test.q_utm, test.pos_radius)
    recalls = recall_at_n(idx, pos, [n for n in ns if n <= k])
    result = {"checkpoint": str(checkpoint), "data": cfg["data"], "num_db": len(db), "num_queries": len(q),
              "pos_radius": test.pos_radius, "recall": {str(n): v for n, v in recalls.items()}}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "recalls.json").write_text(json.dumps(result, indent=1))
        if predictions:
            qn, dn = _names(test, "q"), _names(test, "db")
            with open(out / "predictions.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["query"] + [f"top{i + 1}" for i in range(k)])
                for i, row in enumerate(idx):
                    w.writerow([qn[i]] + [dn[j] for j in row])
        if grid_queries:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            from .plots import retrieval_grid
            qi = list(range(min(grid_queries, len(q))))
            q_imgs = np.asarray(as_image_array(test.q_images)[qi])
            needed = sorted({int(j) for i in qi for j in idx[i, :5]})
            remap = {j: r for r, j in enumerate(needed)}
            db_imgs = np.asarray(as_image_array(test.db_images)[needed])
            sub_pred = np.array([[remap[int(j)] for j in idx[i, :5]] for i in qi])
            sub_pos = [np.array([remap[int(j)] for j in pos[i] if int(j) in remap], dtype=np.int64) for i in qi]
            retrieval_grid(q_imgs, db_imgs, sub_pred, sub_pos, list(range(len(qi))), k=min(5, k))
            plt.savefig(out / "retrieval_grid.png", dpi=100, bbox_inches="tight")
            plt.close("all")
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vpr_nb.evaluate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, help="output folder of python -m vpr_nb.train")
    ap.add_argument("--preset", help="preset name (with --checkpoint, instead of --run)")
    ap.add_argument("--checkpoint", type=Path, help="checkpoint file (default: RUN/checkpoints/best.pt)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--out", type=Path, required=True, help="where recalls.json (and the figure) go")
    ap.add_argument("--predictions", action="store_true", help="also write predictions.csv")
    ap.add_argument("--device", default="auto")
    args = ap.parse_args(argv)
    try:
        if args.run is not None:
            cfg_path = args.run / "config.json"
            if not cfg_path.is_file():
                raise FileNotFoundError(f"{cfg_path} not found: --run must be an output folder of vpr_nb.train")
            base = json.loads(cfg_path.read_text())
            cfg = resolve_config(base["preset"], [])
            cfg.update({k: v for k, v in base.items() if k != "preset"})
            for item in args.overrides:          # re-validate the overrides against the preset's keys
                resolve_config(base["preset"], [item])
                key, value = item.split("=", 1)
                section, name = key.split(".", 1)
                cfg[section][name] = resolve_config(base["preset"], [item])[section][name]
            checkpoint = args.checkpoint or args.run / "checkpoints" / "best.pt"
        elif args.preset and args.checkpoint:
            cfg, checkpoint = resolve_config(args.preset, args.overrides), args.checkpoint
        else:
            ap.error("give --run DIR, or --preset NAME with --checkpoint FILE")
        result = evaluate_checkpoint(cfg, checkpoint, args.out, predictions=args.predictions, device=args.device)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(result["recall"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
