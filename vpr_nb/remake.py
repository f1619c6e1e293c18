"""Re-make one committed number: some arms and seeds of a notebook's on/off experiment, trained alone and printed
beside the committed values.

``make reproduce NOTEBOOK=07 ARMS='cliques*' SEEDS=2`` runs ``python -m vpr_nb.remake 07 --arms 'cliques*'
--seeds 2``: for every results file of notebook 07 made by a package experiment (:data:`EXPERIMENTS`:
``07_premise.json``, ``07_probes.json``, ``07_nearmiss.json``, ``07_paper.json``, ...), the arms whose names match
the pattern train on those seeds only, each at the learning rate the committed file chose (a seed's run at the chosen
rate is the same run whether or not it took part in the choice), and their test Recall@1 is printed beside the
committed one. A single arm and seed takes a few minutes on 2 cores. The experiments a notebook defines in its
own cells (e.g. 07's main table) are re-made by running the notebook: ``make reproduce NOTEBOOK=07``.
"""
from __future__ import annotations

import argparse
import fnmatch
import sys
import time
from collections.abc import Mapping

import torch

from . import results
from .kernels import apply_in_process, is_pinned
from .onoff import (clique, clique_nearmiss, clique_paper, clique_paper_netvlad, clique_paper_salad, clique_probes, dwt,
                    dwt_control, salad, salad_fair)
from .recipe.arms import Selection

# results file -> the package experiment that makes it
EXPERIMENTS = {"03_premise": dwt, "03_control": dwt_control, "05_premise": salad, "05_fair": salad_fair,
               "07_premise": clique, "07_probes": clique_probes, "07_nearmiss": clique_nearmiss,
               "07_paper": clique_paper, "07_paper_salad": clique_paper_salad,
               "07_paper_netvlad": clique_paper_netvlad}


def _flat(doc: Mapping, probes: bool) -> dict:
    """``{(part, world, arm): [R@1 per seed]}`` of an experiment's results (committed or re-made)."""
    arms = doc.get("arms", {})
    if probes and arms and all("R@1" in e for e in arms.values()):     # 07_probes stores one world's arms
        arms = {clique_probes.WORLD: arms}
    out = {("arms", w, a): list(e["R@1"]) for w, ws in arms.items() for a, e in ws.items()}
    out.update({(f"SGD lr {lr}", "off", a): list(e["R@1"]) for lr, ws in doc.get("sgd", {}).items()
                for a, e in ws.items()})
    return out


def remake(notebook: str, arms: str = "*", seeds=None, *, workers: int = 1, echo=print) -> list[dict]:
    """Re-make the arms matching ``arms`` on ``seeds`` (None: all) of every package experiment of ``notebook``
    (``"07"``); returns the rows printed (``committed`` vs ``re-made`` test R@1 per arm and seed)."""
    text = str(notebook).strip()
    files = [n for n in EXPERIMENTS if text.isdigit() and n.startswith(f"{int(text):02d}_")]
    if not files:
        raise ValueError(f"notebook {notebook!r} has no experiment that can be re-made arm by arm; these have: "
                         f"{', '.join(sorted({n[:2] for n in EXPERIMENTS}))} (a whole notebook: make reproduce "
                         f"NOTEBOOK=NN)")
    rows = []
    for name in files:
        module, probes = EXPERIMENTS[name], name == "07_probes"
        doc = results.load(name, module.EXPERIMENT)["results"]
        committed = _flat(doc, probes)
        all_seeds = tuple(module.EXPERIMENT.get("seeds") or clique.SEEDS)
        if not any(fnmatch.fnmatchcase(arm, arms) for _, _, arm in committed):
            echo(f"{name}: no arm matches {arms!r} (arms: {', '.join(sorted({a for _, _, a in committed}))})")
            continue
        lrs = {w: {a: committed_lr for (part, w2, a), committed_lr in _lrs(doc, probes).items() if w2 == w}
               for w in {w for _, w, _ in committed}}
        kept = None if seeds is None else [s for s in seeds if s in all_seeds]
        if kept is not None and len(kept) < len(seeds):     # e.g. 03's control has 5 seeds, its premise file 8
            echo(f"{name}: seeds {[s for s in seeds if s not in all_seeds]} are not among its seeds "
                 f"{list(all_seeds)}" + ("; skipped" if not kept else ""))
            if not kept:
                continue
        select = Selection(arms, None if kept is None else tuple(kept), lrs)
        chosen = select.seeds or all_seeds
        echo(f"{name}: re-making arms {arms!r}, seeds {list(chosen)} ...")
        t0 = time.perf_counter()
        extra = {"baseline": {a: {"R@1": v} for a, v in doc["paired with"].items()}} if probes else {}
        remade = _flat(module.run(seeds=all_seeds, workers=workers, select=select, **extra), False)
        echo(f"{name}: {time.perf_counter() - t0:.0f} s")
        for key, values in remade.items():
            for seed, value in zip(chosen, values):
                rows.append({"file": name, "part": key[0] if key[0] != "arms" else f"premise {key[1]}",
                             "arm": key[2], "seed": seed, "committed": committed[key][all_seeds.index(seed)],
                             "re-made": value})
    if not rows:
        raise ValueError(f"no arm of notebook {notebook}'s experiments matches {arms!r}"
                         + ("" if seeds is None else f" on seeds {list(seeds)}"))
    width = max(len(r["arm"]) for r in rows)
    echo(f"\n{'file':11s} {'part':13s} {'arm':{width}s} seed  committed  re-made  difference")
    for r in rows:
        diff = r["re-made"] - r["committed"]
        echo(f"{r['file']:11s} {r['part']:13s} {r['arm']:{width}s} {r['seed']:4d}  {r['committed']:9.4f}  "
             f"{r['re-made']:7.4f}  {'equal' if diff == 0 else f'{diff:+.4f}'}")
    return rows


def _lrs(doc: Mapping, probes: bool) -> dict:
    """``{(part, world, arm): the committed lr}`` of the arms (the SGD table trains at its own fixed rates)."""
    arms = doc.get("arms", {})
    if probes:
        arms = {clique_probes.WORLD: arms}
    return {("arms", w, a): float(e["lr"]) for w, ws in arms.items() for a, e in ws.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vpr_nb.remake", description=__doc__.split("\n\n")[0])
    parser.add_argument("notebook", help="the notebook's number, e.g. 07")
    parser.add_argument("--arms", default="*", help="a shell pattern over arm names, e.g. 'cliques*' (default: all)")
    parser.add_argument("--seeds", default=None, help="seeds, comma-separated, e.g. 2 or 0,3 (default: all)")
    parser.add_argument("--workers", type=int, default=1, help="local processes for the fine-tunes (default 1)")
    args = parser.parse_args(argv)
    if not is_pinned():
        print("note: the CPU kernels are not pinned, so the numbers may differ from the committed ones; run it as "
              "python -m vpr_nb.kernels --run python -m vpr_nb.remake ... (make reproduce does)", file=sys.stderr)
    apply_in_process()
    torch.set_num_threads(1)
    try:
        seeds = None if args.seeds in (None, "") else [int(s) for s in str(args.seeds).replace(" ", "").split(",")]
        if args.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {args.workers}")
        rows = remake(args.notebook, args.arms, seeds, workers=args.workers)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0 if all(r["re-made"] == r["committed"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
