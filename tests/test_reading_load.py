"""The reading load of every notebook: prose words, sentence length, words per figure.

A student reads the markdown cells. Measured here: prose words (headings, tables, code spans and maths count
as one word each or nothing, see :func:`prose`) and, cruder, every word of the markdown (:func:`all_words`);
the 90th percentile and the longest sentence in words; prose words per stored figure. Limits: at most 2,200
words a notebook by either count, a p90 sentence of at most 30 words and none over 50, and at most 600 prose
words per figure (the teaching anchors: UvA deep-learning tutorials, d2l). ``python tests/test_reading_load.py``
prints the table."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.ipynb"))
MAX_WORDS, MAX_P90, MAX_SENTENCE, MAX_WORDS_PER_FIGURE = 2200, 30, 50, 600
WORD = re.compile(r"[A-Za-z0-9][\w'’.-]*")


def prose(markdown: str) -> str:
    """The text a student reads as sentences: no headings, tables, HTML comments or link targets; display maths,
    inline maths and code spans are one word each."""
    text = re.sub(r"<!--.*?-->", " ", markdown, flags=re.S)
    text = re.sub(r"\$\$.*?\$\$", " MATH ", text, flags=re.S)
    text = re.sub(r"\$[^$\n]+\$", "MATH", text)
    text = re.sub(r"`[^`\n]+`", "CODE", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)                       # [label](target): the label only
    text = re.sub(r"https?://\S+", "LINK", text)
    lines = [line for line in text.splitlines()
             if not line.lstrip().startswith(("#", "|")) and not re.fullmatch(r"\s*[-=:| ]{3,}\s*", line)]
    return "\n".join(lines)


def sentences(text: str) -> list[str]:
    """Sentences: split at . ! ? followed by a space, at blank lines and at list items."""
    parts = re.split(r"(?<=[.!?])\s+(?=[A-Z0-9*(\"'`])|\n\s*\n|\n\s*(?:[*-]|\d+\.)\s+", text)
    return [p for p in parts if WORD.search(p)]


def all_words(nb: dict) -> int:
    """The cruder count: every letter-word of every markdown cell, headings, tables and maths included (fenced code
    excluded). A notebook keeps both counts within :data:`MAX_WORDS`."""
    text = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "markdown")
    return len(re.findall(r"[A-Za-z][A-Za-z'-]*", re.sub(r"```.*?```", " ", text, flags=re.S)))


def measure(nb: dict) -> dict:
    text = "\n\n".join(prose("".join(c["source"])) for c in nb["cells"] if c["cell_type"] == "markdown")
    lengths = [len(WORD.findall(s)) for s in sentences(text)] or [0]
    figures = sum("image/png" in o.get("data", {}) for c in nb["cells"] if c["cell_type"] == "code"
                  for o in c.get("outputs", []))
    words = len(WORD.findall(text))
    return {"words": words, "all markdown words": all_words(nb), "p90 sentence": int(np.percentile(lengths, 90)), "longest sentence": max(lengths),
            "figures": figures, "words per figure": round(words / max(figures, 1))}


def _read(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def test_the_measure_counts_prose_only():
    md = ("## A heading that is not counted\n\nOne short sentence here. Another one, with `code()` and $x^2$.\n\n"
          "| a | b |\n|---|---|\n| 1 | 2 |\n\n- a list item of six words\n")
    nb = {"cells": [{"cell_type": "markdown", "source": md},
                    {"cell_type": "code", "source": "", "outputs": [{"data": {"image/png": "x"}}]}]}
    got = measure(nb)
    assert got["words"] == 4 + 6 + 6 and got["figures"] == 1 and got["longest sentence"] == 6
    assert got["all markdown words"] == 6 + 4 + 6 + 2 + 6       # heading, sentences (code and maths too), table, list


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem[:2] for p in NOTEBOOKS])
def test_reading_load(path):
    got = measure(_read(path))
    over = [f"{k} {got[k]} > {limit}" for k, limit in (("words", MAX_WORDS), ("all markdown words", MAX_WORDS),
                                                         ("p90 sentence", MAX_P90),
                                                         ("longest sentence", MAX_SENTENCE),
                                                         ("words per figure", MAX_WORDS_PER_FIGURE))
            if got[k] > limit]
    assert not over, f"{path.name}: {', '.join(over)} (shorten the prose; history and justifications go to docs/)"


if __name__ == "__main__":
    for p in NOTEBOOKS:
        m = measure(_read(p))
        print(p.stem[:2], "  ".join(f"{k} {v}" for k, v in m.items()))
    sys.exit(0)
