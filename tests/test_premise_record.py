"""The premise record (vpr_nb.premise.record), the on/off arms' pieces (vpr_nb.recipe.arms, TripletBatches),
and the stored premise notebooks: every verdict they print and state follows the stored numbers."""
from __future__ import annotations

import json
import re
from pathlib import Path

import nbformat
import numpy as np
import pytest

from vpr_nb.premise.record import (paired_differences, premise_record, premise_verdicts, record_problems,
                                   verdict_lines)
from vpr_nb.onoff import clique as onoff_clique
from vpr_nb.onoff import dwt_control
from vpr_nb.onoff import salad_fair
from vpr_nb.verdict import WORDS as VERDICTS, gap

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "notebooks" / "results"
# premise results file -> the stored notebook that shows it
PREMISE_FILES = {"03_premise.json": "03_distance_ranking_weighted_loss.ipynb",
                 "03_control.json": "03_distance_ranking_weighted_loss.ipynb",
                 "05_premise.json": "05_salad.ipynb",
                 "05_fair.json": "05_salad.ipynb",
                 "07_premise.json": "07_clique_mining.ipynb"}


def _record(diffs_on=(0.03, 0.04, 0.02, 0.05, 0.03), diffs_off=(0.01, -0.01, 0.0, 0.02, -0.02), queries=1749):
    return premise_record("cv of w", "not found",
                          {"on": {"value": 0.9, "test queries": queries}, "off": {"value": 0.03, "test queries": queries}},
                          {"A − B": {"on": list(diffs_on), "off": list(diffs_off)}})


def test_gap_is_mean_and_standard_error_of_paired_differences():
    d = [0.03, 0.04, 0.02, 0.05, 0.03]
    m, se = gap(d)
    assert m == pytest.approx(np.mean(d)) and se == pytest.approx(np.std(d, ddof=1) / np.sqrt(5))
    assert paired_differences([0.9, 0.8], [0.85, 0.82]) == [0.05, -0.02]


def test_premise_verdicts_are_one_family_over_comparisons_and_worlds():
    # each alone would "help" (t 3.7, p 0.022); Holm over the 4 comparisons of the record (2 × 2 worlds): p 0.087
    modest, null = [0.02, 0.03, 0.0, 0.03, 0.02], [0.01, -0.01, 0.0, 0.02, -0.02]
    rec = premise_record("q", "not found", {w: {"value": 1, "test queries": 1000} for w in ("on", "off")},
                         {"A − B": {"on": modest, "off": null}, "C − B": {"on": null, "off": null}})
    family = premise_verdicts(rec)
    assert list(family) == ["A − B, premise on", "A − B, premise off", "C − B, premise on", "C − B, premise off"]
    assert {v.family for v in family.values()} == {4}
    assert family["A − B, premise on"].word == "no measurable effect" and family["A − B, premise on"].p < 0.05
    assert verdict_lines(rec)[-1] == "Holm over the 4 comparisons of this table"


def test_record_is_checked():
    rec = _record()
    assert record_problems(rec) == []
    assert verdict_lines(rec) == [
        "A − B, premise on: +0.034 ± 0.005 (5 seeds, t 6.7, Holm p 0.005 over 2 comparisons): helps",
        "A − B, premise off: +0.000 ± 0.007 (5 seeds, t 0.0, Holm p 1.000 over 2 comparisons): no measurable effect",
        "Holm over the 2 comparisons of this table"]
    assert record_problems(_record(diffs_on=(0.1, 0.2))) == ["A − B, premise on: 2 paired seeds, fewer than 5"]
    assert "test queries" in record_problems(_record(queries=318))[0]
    with pytest.raises(ValueError, match="worlds must have exactly"):
        premise_record("q", "not found", {"on": {"value": 1, "test queries": 5}}, {"A − B": {"on": [1], "off": [1]}})
    with pytest.raises(ValueError, match="NaN"):
        _record(diffs_on=(0.1, float("nan")))
    with pytest.raises(ValueError, match="real_data"):
        premise_record("q", "unknown", {"on": {"value": 1, "test queries": 5}, "off": {"value": 1, "test queries": 5}},
                       {"A − B": {"on": [1], "off": [1]}})


def test_pooled_recall_weights_each_split_by_its_counted_queries():
    from vpr_nb.recipe.arms import counted_queries, pooled_recall
    from vpr_nb.synthetic import make_dataset
    ds = make_dataset("city", seed=0, splits=("val", "test"))
    from vpr_nb.evaluation import evaluate_on_split, raw_pixel_descriptors
    pix = raw_pixel_descriptors
    parts = [(evaluate_on_split(pix(s.db_images), pix(s.q_images), s, (1,))[1], counted_queries(s))
             for s in (ds.val, ds.test)]
    pooled = pooled_recall(None, [ds.val, ds.test], (1,), descriptors=pix)
    assert pooled["queries"] == sum(n for _, n in parts)
    assert pooled[1] == pytest.approx(sum(r * n for r, n in parts) / sum(n for _, n in parts))
    with pytest.raises(ValueError, match="at least one test split"):
        pooled_recall(None, [], (1,), descriptors=pix)


def test_triplet_batches_draw_random_positives_within_their_radius():
    import dataclasses

    from vpr_nb.recipe import RECIPE, TripletBatches
    from vpr_nb.synthetic import make_dataset
    tr = make_dataset("city", seed=0, splits=("train",)).train
    src = TripletBatches("t", "random", 15.0)(tr, RECIPE, None)
    assert src.positive == "random" and src.split.train_pos_radius == 15.0 and tr.train_pos_radius == 10.0
    assert dataclasses.replace(tr).train_pos_radius == 10.0
    with pytest.raises(ValueError):
        TripletBatches("t", "nearest")
    with pytest.raises(ValueError):
        TripletBatches("t", "random", -1.0)


def _outputs(nb) -> str:
    out = []
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            out.append(o.get("text", "") if o.get("output_type") == "stream" else o.get("data", {}).get("text/plain", ""))
    return "\n".join(out)


def _stated_verdicts(text: str, names) -> list[tuple[str, str, str | None]]:
    """``(comparison, world, the first verdict word after it in its line or None)`` for every place the text
    names a comparison and a world as ``"<comparison>, premise on"`` (markup such as ``*`` in between is allowed)."""
    found = []
    for name in names:
        for m in re.finditer(re.escape(name) + r"[*_]*,\s*premise\s+(on|off)\b", text):
            rest = text[m.end():].split("\n", 1)[0]
            hits = sorted((rest.find(v), v) for v in (*VERDICTS, "inconclusive") if v in rest)
            found.append((name, m.group(1), hits[0][1] if hits else None))
    return found


def _verdict_problems(record, outputs: str, markdown: str, gates=None) -> list[str]:
    """What the stored notebook gets wrong about ``record``: a verdict line (recomputed from the stored per-seed
    differences by today's rule, one Holm family per record) that its outputs do not print, or a sentence of its
    text that states another word than the recomputed one."""
    family = premise_verdicts(record, gates)
    problems = [f"does not print {line!r}" for line in verdict_lines(record, gates) if line not in outputs]
    stated = _stated_verdicts(markdown, record["comparisons"])
    for name, world, said in stated:
        want = family[f"{name}, premise {world}"]
        if said != want.word:
            problems.append(f"the text says {name}, premise {world}: {said!r}; the stored numbers give "
                            f"{want.word!r} ({want.text()})")
    if not stated:
        problems.append("the text states no premise verdict")
    return problems


def _stored(results_file):
    path = RESULTS / results_file
    if not path.exists():
        pytest.skip(f"{results_file} is not committed yet")
    results = json.loads(path.read_text(encoding="utf-8"))["results"]
    nb = nbformat.read(ROOT / "notebooks" / PREMISE_FILES[results_file], as_version=4)
    return results["premise"], _outputs(nb), _scope(nb, results_file.removesuffix(".json")), \
        GATES.get(results_file, lambda _results: None)(results)


def _scope(nb, stem: str) -> str:
    """The markdown that reads the results file ``stem``: from the code cell that loads it up to the next code
    cell that loads another results file (a notebook with two premise files states each one's verdicts there)."""
    loads = re.compile(r"results\.(?:load|made_or_loaded)\(\s*[\"']([\w-]+)[\"']")
    inside, text = False, []
    for cell in nb.cells:
        if cell.cell_type == "code":
            found = loads.findall(cell.source)
            if found:
                inside = stem in found
        elif inside:
            text.append(cell.source)
    return "\n".join(text)


# the premise files whose notebook gates a comparison on its fine-tuned baseline (07: the paper's comparison)
GATES = {"07_premise.json": onoff_clique.premise_gates,
         "03_control.json": lambda results: dwt_control.gates(results["arms"]),
         "05_fair.json": salad_fair.gates}


@pytest.mark.parametrize("results_file", sorted(PREMISE_FILES))
def test_stored_premise_records_and_their_verdicts(results_file):
    record, outputs, markdown, gates = _stored(results_file)
    assert record_problems(record) == []
    problems = _verdict_problems(record, outputs, markdown, gates)
    assert not problems, f"{PREMISE_FILES[results_file]} against {results_file}: {problems}"


def test_every_premise_file_is_checked():
    with_record = {p.name for p in RESULTS.glob("*.json")
                   if "comparisons" in (json.loads(p.read_text("utf-8"))["results"].get("premise") or {})}
    assert with_record <= set(PREMISE_FILES)


def test_each_premise_file_is_read_where_its_notebook_loads_it():
    nb = nbformat.read(ROOT / "notebooks" / PREMISE_FILES["07_premise.json"], as_version=4)
    scope = _scope(nb, "07_premise")
    assert "premise on" in scope and scope not in _scope(nb, "07_probes")


def test_a_flipped_word_is_caught():
    record, outputs, markdown, gates = _stored("07_premise.json")
    name = list(record["comparisons"])[1]                       # the mining-only ablation (not gated)
    word = premise_verdicts(record, gates)[f"{name}, premise on"].word
    other = next(v for v in VERDICTS if v != word)
    line = next(ln for ln in verdict_lines(record, gates) if ln.startswith(f"{name}, premise on:"))
    printed = outputs.replace(line, line[: -len(word)] + other)
    assert any("does not print" in p for p in _verdict_problems(record, printed, markdown, gates))
    stated = markdown.replace(f"{name}, premise on*: {word}", f"{name}, premise on*: {other}")
    assert stated != markdown and any("the text says" in p for p in _verdict_problems(record, outputs, stated, gates))


def test_a_failed_gate_makes_the_papers_comparison_inconclusive():
    record, _, _, gates = _stored("07_premise.json")
    family = premise_verdicts(record, gates)
    for world in ("on", "off"):
        gate = gates[f"sparse + dense cliques − sparse only, premise {world}"]
        assert (family[f"sparse + dense cliques − sparse only, premise {world}"].word == "inconclusive") \
            == (not gate.passed)


def test_stated_verdicts_are_read_in_text_order():
    text = "* *A − B, premise on*: no measurable effect here, where it helps elsewhere\n* A − B, premise off: hurts"
    assert _stated_verdicts(text, ["A − B"]) == [("A − B", "on", "no measurable effect"), ("A − B", "off", "hurts")]
