"""Every number a notebook's Takeaways state is one its own stored outputs show.

A Takeaways section is the text under a ``## Takeaways`` heading of a markdown cell, up to the next
``## `` heading or the end of the cell. The rule, applied by :func:`unbacked_numbers`:

**Which numbers are checked** (after the text listed under "not checked" is removed):

* every decimal (``0.748``, ``± 0.007``, ``−0.025``, ``9.4``), every percentage (``12 %``) and every
  integer of 10 or more (``803 queries``, ``110 m``, ``+14 points``);
* integers below 10 are not checked (counts of the set-up: "3 epochs", "5 seeds", "4 headings").

**Not checked**, because they are not results of the notebook:

* equation, figure, table, exercise, section and notebook numbers: ``Eq. (4)``, ``Eqs. (5)–(8)``,
  ``Eq. 3``, ``Figure 2``, ``Table III``, ``Exercise 4``, ``notebooks 03–07``, and any integer written with a
  leading zero (``05``: the course numbers its notebooks that way);
* years (integers 1900–2099 with four digits);
* numbers that are part of a name: glued to a letter (``VGG16``, ``conv5``, ``30k``, ``1e-3``), after a
  letter and a hyphen (``NetVLAD-16``, ``top-5``) or after ``@`` (``R@10``);
* inline code (`` `max_heading_diff=45` ``, ``<code>…</code>``) and LaTeX math (``$M \\cdot m$``,
  ``$10^{-4}$``): settings and formulas, not measurements;
* a clause that quotes a paper: from the word "paper" ("papers", "paper's", "paper:") to the end of its
  clause (the next ``;``, ``:``, ``)``, sentence end, or comma followed by "and", "but", "not", "so",
  "where" or "while"), e.g. "(the paper: Max-W 3 points above Max)", "paper 0.812, 0.811, 0.797, 0.826)",
  "the paper reports 90 R@1.".

**What backs a number**: a number of the notebook's outputs (stream text, ``text/plain``,
``text/markdown``, ``text/html``) of which the stated number is a rounding, i.e. within half a unit of
its last digit (``9.4`` is backed by ``9.44``, ``110 m`` by ``110.0``), or a number of a markdown cell
marked as the paper's (a heading line or a table header row that contains "paper"). Signs are not
compared: a takeaway may state a difference either way round ("Mean beats Max by +0.015" for the
output's "Max − Mean = -0.015"). A percentage or a number of "points" is also backed by an output
fraction 100 times smaller (``11 points`` by ``+0.109``). Numbers with few digits are therefore checked
loosely (``15 points`` is backed by any output from 0.145 to 0.155): the test catches a number that no
output shows, not every slip of a rounding. It runs on every notebook, 00 included.
"""
from __future__ import annotations

import re
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))

_REFERENCE = re.compile(   # Eq. (4), Eqs. (5)–(8), Figure 2, Table 3, notebooks 03–07, Exercise 1 and 2, ...
    r"\b(?:eqs?\.|equations?|figs?\.|figures?|tables?|exercises?|secs?\.|sections?|notebooks?|steps?)"
    r"\s*\(?\d+\)?(?:\s*(?:[–-]|,|and|or|to)\s*\(?\d+\)?)*", re.I)
_CODE = re.compile(r"`[^`]*`|<code>.*?</code>", re.S)
_MATH = re.compile(r"\$\$.*?\$\$|\$[^$]*\$", re.S)
_LINK_TARGET = re.compile(r"\]\([^)]*\)|https?://\S+")
_PAPER_CLAUSE = re.compile(r"\bpapers?(?:'s)?\b:?.*?(?=[;:)]|,\s+(?:and|but|not|so|where|while)\b|\.(?:[\s*_]|$)|$)",
                           re.I | re.S)
_NUMBER = re.compile(r"([+\-−]?)(\d{1,3}(?:,\d{3})+(?!\d)|\d+)(\.\d+)?(\s?%|\s+points?\b)?")
_OUTPUT_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def takeaways(nb) -> list[str]:
    """The text of every ``## Takeaways`` section of ``nb``'s markdown cells."""
    found = []
    for cell in nb.cells:
        if cell.cell_type != "markdown":
            continue
        for m in re.finditer(r"^## Takeaways[^\n]*\n(.*?)(?=^## |\Z)", cell.source, flags=re.M | re.S):
            found.append(m.group(1))
    return found


def _blank(pattern: re.Pattern, text: str) -> str:
    """Replace every match by spaces (so that what stays keeps its neighbours apart)."""
    return pattern.sub(lambda m: " " * len(m.group(0)), text)


def stated_numbers(text: str) -> list[tuple[str, float, int, str]]:
    """The numbers of ``text`` the rule checks: (as written, absolute value, decimals, unit '' / '%' / 'points')."""
    for pattern in (_CODE, _MATH, _LINK_TARGET, _REFERENCE, _PAPER_CLAUSE):
        text = _blank(pattern, text)
    out = []
    for m in _NUMBER.finditer(text):
        sign, whole, frac, unit = m.group(1), m.group(2), m.group(3) or "", (m.group(4) or "").strip()
        written = m.group(0).strip()
        before = text[m.start() - 1] if m.start() > 0 else " "
        if sign == "-" and before.isalnum():                  # a hyphen, not a sign:
            if before.isalpha():
                continue                                      # 'NetVLAD-16', 'top-5': part of a name
            written, before = written[1:], "-"                # '1-16': a range
        if before.isalnum() or before in "_@^./\\#":          # part of a name or of a longer token
            continue
        end = m.end(3) if frac else m.end(2)
        after = text[end] if end < len(text) else " "
        if (after.isalpha() and not (after in "x×" and not text[end + 1:end + 2].isalpha())) or after == "_":
            continue                                          # 'VGG16'-like names, '30k', '1e-3'; '1.6x' is a number
        if not frac and whole.startswith("0") and len(whole) > 1:
            continue                                          # '05': a notebook number
        value = float(whole.replace(",", "") + frac)
        if not frac and not unit and value < 10:
            continue                                          # small counts of the set-up
        if not frac and len(whole) == 4 and 1900 <= value <= 2099:
            continue                                          # a year
        out.append((written, value, len(frac) - 1 if frac else 0, "points" if "point" in unit else unit))
    return out


def backing_numbers(nb) -> list[float]:
    """Every number of ``nb``'s outputs and of its markdown cells marked as the paper's."""
    texts = []
    for cell in nb.cells:
        if cell.cell_type == "code":
            for o in cell.get("outputs", []):
                if o.get("output_type") == "stream":
                    texts.append(o.get("text", ""))
                for kind in ("text/plain", "text/markdown", "text/html"):
                    value = o.get("data", {}).get(kind)
                    if value:
                        texts.append(value if isinstance(value, str) else "".join(value))
        elif cell.cell_type == "markdown":
            lines = cell.source.splitlines()
            headers = [ln for ln in lines if ln.startswith("#")] + _table_headers(cell.source)
            marked = any(re.search("paper", ln, re.I) for ln in headers)
            if marked:
                texts.append(cell.source)
    return [float(t) for text in texts for t in _OUTPUT_NUMBER.findall(text.replace(",", ""))]


def _table_headers(source: str) -> list[str]:
    """The header row of every markdown table of ``source`` (the line above a ``|---|`` line)."""
    lines = source.splitlines()
    return [lines[i - 1] for i, ln in enumerate(lines) if i > 0 and re.match(r"\|\s*:?-{3,}", ln)]


def is_backed(value: float, decimals: int, unit: str, backing: list[float]) -> bool:
    """``value`` (as stated, with ``decimals`` digits) is a rounding of some backing number."""
    half = 0.5 * 10.0 ** -decimals + 1e-9
    scales = (1.0, 100.0) if unit in ("%", "points") else (1.0,)
    return any(abs(abs(y) * s - value) <= half for y in backing for s in scales)


def unbacked_numbers(nb) -> list[str]:
    """The numbers of ``nb``'s Takeaways that none of its outputs (or paper cells) backs, as written."""
    backing = backing_numbers(nb)
    return [written for text in takeaways(nb) for written, value, decimals, unit in stated_numbers(text)
            if not is_backed(value, decimals, unit, backing)]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_every_takeaway_number_is_in_an_output(path):
    nb = nbformat.read(path, as_version=4)
    assert takeaways(nb), f"{path.name}: no '## Takeaways' section"
    missing = unbacked_numbers(nb)
    assert not missing, (f"{path.name}: the Takeaways state {missing}, which no output of the notebook shows "
                         "(nor a markdown cell marked as the paper's): fix the text to match the stored outputs")


# --- the checker itself, on tiny fake notebooks -----------------------------------------------------------

def _fake(output: str, takeaway: str, extra_markdown: str | None = None):
    nb = nbformat.v4.new_notebook()
    code = nbformat.v4.new_code_cell("print(...)")
    code.outputs = [nbformat.v4.new_output("stream", name="stdout", text=output)]
    nb.cells = [code] + ([nbformat.v4.new_markdown_cell(extra_markdown)] if extra_markdown else []) + [
        nbformat.v4.new_markdown_cell("## Exercises\n\n1. Try 0.999.\n\n## Takeaways\n\n" + takeaway + "\n\n## Next")]
    return nb


def test_checker_finds_a_number_that_no_output_shows():
    nb = _fake("R@1 0.748 +0.030 ± 0.005", "* R@1 reaches 0.748 (+0.030 ± 0.005), and 0.812 with more seeds.")
    assert unbacked_numbers(nb) == ["0.812"]


def test_checker_reads_only_the_takeaways_section():
    nb = _fake("R@1 0.748", "* R@1 0.748.")        # 0.999 sits in the Exercises of the same cell
    assert unbacked_numbers(nb) == []


def test_checker_accepts_roundings_magnitudes_percentages_and_points():
    nb = _fake("ratio 9.44, distance 414.7 m, Max − Mean = -0.015 ± 0.005, gain +0.109, share 0.125",
               "* about 9.4, 415 m apart; Mean beats Max (+0.015 ± 0.005); about 11 points; 12.5 % of them.")
    assert unbacked_numbers(nb) == []
    assert unbacked_numbers(_fake("ratio 9.44", "* about 9.5.")) == ["9.5"]
    assert unbacked_numbers(_fake("gain +0.109", "* about 12 points.")) == ["12 points"]


def test_checker_skips_references_names_code_math_years_and_paper_quotes():
    text = ("* Eq. (4), Eqs. (5)–(8), Figure 12, Table 10 and notebooks 03–07 (CVPR 2024); NetVLAD-16 on VGG16, "
            "R@10, `max_heading_diff=45`, $10^{-4}$, 3 epochs and 5 seeds; the paper: Max-W 3.2 points above "
            "Max (paper 0.826); the paper reports 90 R@1.")
    assert stated_numbers(text) == []
    assert unbacked_numbers(_fake("nothing", text)) == []


def test_checker_accepts_a_paper_table_in_markdown():
    nb = _fake("R@1 0.748", "* ours 0.748, theirs 81.2.",
               extra_markdown="## The paper's table\n\n| method | R@1 |\n|---|---|\n| T-Loss | 81.2 |")
    assert unbacked_numbers(nb) == []
    assert unbacked_numbers(_fake("R@1 0.748", "* ours 0.748, theirs 81.2.")) == ["81.2"]


def test_a_paper_quote_ends_with_its_clause():
    text = ("* **At the paper's learning rate the factor trains.** T-Loss moves (+0.030 ± 0.005); range 1-16 epochs;"
            " the paper's single runs, and standard errors of 0.005 to 0.011.")
    assert [w for w, *_ in stated_numbers(text)] == ["+0.030", "0.005", "16", "0.005", "0.011"]
