"""What a student reads: no development history, figures captioned, hints and self-checks, widgets that
show something without a kernel (notebooks/*.ipynb and their paired scripts)."""
import re
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]
ALL = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
COURSE = [p for p in ALL if "02" <= p.name[:2] <= "08"]      # the graded notebooks
WIDGET_CELLS = {"03_distance_ranking_weighted_loss.ipynb": "distance_weight_explorer(", "06_gds.ipynb": "widgets.interact("}

HISTORY = {   # pattern: what it catches
    r"\bissue\s*#?\s*\d+": "an issue number",
    r"\bthe issue\b": "a reference to an issue",
    r"\bbefore the fix\b|\bafter the fix\b": "development history",
    r"\bprevious version\b|\bold notebook\b|\bearlier version\b": "development history",
    r"\bgit (show|log|diff|checkout)\b": "a git command into the history",
    r"(?<![\w./-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![\w/-])": "a commit hash",
    r"(?<![\w.~-])/(work|root|home|Users|tmp|mnt)/": "a machine path",
}


def _sources(path):
    nb = nbformat.read(path, as_version=4)
    return [(i, c) for i, c in enumerate(nb.cells) if c.cell_type in ("markdown", "code")]


@pytest.mark.parametrize("path", ALL, ids=lambda p: p.name)
def test_student_text_has_no_development_history(path):
    found = []
    for i, cell in _sources(path):
        for pattern, what in HISTORY.items():
            for m in re.finditer(pattern, cell.source, flags=re.I if "hash" not in what else 0):
                found.append(f"cell {i} ({cell.cell_type}): {what}: {cell.source[max(0, m.start() - 40):m.end() + 40]!r}")
    assert not found, f"{path.name}:\n" + "\n".join(found)


def _makes_figure(cell) -> bool:
    return any(k.startswith("image/") for o in cell.get("outputs", []) for k in o.get("data", {}))


@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_every_figure_has_a_numbered_caption_right_under_it(path):
    nb = nbformat.read(path, as_version=4)
    numbers = []
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code" and _makes_figure(cell):
            below = nb.cells[i + 1] if i + 1 < len(nb.cells) else None
            m = re.match(r"\*\*Figure (\d+)", below.source) if below is not None and below.cell_type == "markdown" else None
            assert m, f"{path.name}: the figure of cell {i} has no caption cell (**Figure N.** ...) right under it"
            numbers.append(int(m.group(1)))
    captions = [int(m.group(1)) for c in nb.cells if c.cell_type == "markdown"
                for m in [re.match(r"\*\*Figure (\d+)", c.source)] if m]
    assert captions == list(range(1, len(captions) + 1)), f"{path.name}: figures numbered {captions}"
    assert set(numbers) <= set(captions) and numbers, f"{path.name}: no captioned figure"


@pytest.mark.parametrize("name", sorted(WIDGET_CELLS))
def test_widget_cells_store_a_static_rendering_of_their_default_state(name):
    nb = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    cell = next(c for c in nb.cells if c.cell_type == "code" and WIDGET_CELLS[name] in c.source)
    assert _makes_figure(cell), f"{name}: the widget cell stores no static figure of its default state"
    assert any("default state" in o.get("text", "") for o in cell.outputs), f"{name}: the static rendering is not labelled"


def _exercise_items(nb):
    """The numbered items of the ungraded "## Exercises" list."""
    for cell in nb.cells:
        if cell.cell_type == "markdown" and "## Exercises" in cell.source:
            body = cell.source.split("## Exercises", 1)[1].split("\n## ", 1)[0]
            return [it for it in re.split(r"\n(?=\d+\. )", "\n" + body.strip()) if re.match(r"\d+\. ", it.strip())]
    return []


@pytest.mark.parametrize("path", COURSE, ids=lambda p: p.name)
def test_every_ungraded_exercise_has_a_hint_and_the_notebook_ends_with_three_self_checks(path):
    nb = nbformat.read(path, as_version=4)
    items = _exercise_items(nb)
    assert items, f"{path.name}: no ## Exercises list"
    for item in items:
        assert "<details><summary>Hint</summary>" in item and "</details>" in item, \
            f"{path.name}: exercise without a hint: {item[:80]!r}"
    md = [(i, c.source) for i, c in enumerate(nb.cells) if c.cell_type == "markdown"]
    checks = [i for i, src in md if src.startswith("## Self-check")]
    assert len(checks) == 1, f"{path.name}: expected one ## Self-check section, found {len(checks)}"
    body = max(i for i, src in md if "## Exercises" in src or "## Takeaways" in src)
    assert checks[0] > body, f"{path.name}: the self-check must come after the exercises and takeaways"
    after = [src.split("\n", 1)[0] for i, src in md if i > checks[0] and src.startswith("## ")]
    assert after in ([], ["## References"]), f"{path.name}: sections after the self-check: {after}"
    text = nb.cells[checks[0]].source
    questions = re.findall(r"^\d+\. ", text, flags=re.M)
    answers = text.count("<details><summary>Answer</summary>")
    assert len(questions) == 3 and answers == 3, f"{path.name}: {len(questions)} self-check questions, {answers} answers"


# Prose a student reads needs no knowledge of the package's layout: no module path (``vpr_nb.recipe.x``), no
# maintainer file (``docs/notes/...``) and no arm code (``R07``). Allowed: a ``python -m vpr_nb.x`` command, the
# package's name alone, the "Use `vpr_nb`" sections (they name what the next cell calls) and folded hints.
JARGON = {r"(?<!-m )\bvpr_nb\.[a-z_]+\.[A-Za-z_]": "a module path", r"\bdocs/": "a maintainer file",
          r"\bR0\d\b": "an arm code"}


def _prose(cell) -> str:
    text = re.sub(r"<details>.*?</details>", "", cell.source, flags=re.S)
    return "" if text.lstrip().startswith("## Use `vpr_nb`") else text


@pytest.mark.parametrize("path", ALL, ids=lambda p: p.name)
def test_prose_names_no_module_path_file_or_arm_code(path):
    found = [f"cell {i}: {what}: {m.group(0)!r} in {_prose(c)[max(0, m.start() - 40):m.end() + 30]!r}"
             for i, c in _sources(path) if c.cell_type == "markdown"
             for pattern, what in JARGON.items() for m in re.finditer(pattern, _prose(c))]
    assert not found, f"{path.name}:\n" + "\n".join(found)
