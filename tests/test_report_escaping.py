"""vpr_nb.report renders recorded strings and keys as text: no tag, link, image, code span or autolink in
``results.md`` (as Markdown, or pasted into HTML) can come from a recorded result, and a value that is not a
finite number is marked ``**⚠ NaN**`` / ``**⚠ inf**``, never printed as an ordinary number."""
from __future__ import annotations

import math
import re

import markdown_it
import mistune
import pytest

from vpr_nb.report import escape_markdown, format_value, render_markdown, render_table

HOSTILE = [
    "<script>alert(1)</script>",
    "<img src=x onerror=alert(1)>",
    "[click](javascript:alert(1))",
    "![](http://evil.example/x.png)",
    "![x][ref]\n\n[ref]: https://evil.example/y.png",
    "<javascript:alert(1)>",
    "<https://evil.example>",
    "see https://evil.example/a, HTTP://EVIL.EXAMPLE and www.evil.example",
    "mail me@evil.example.com",
    "`code` and ``more``",
    "a|b",
    "trailing backslash \\",
    "\\[x](javascript:alert(1))",
    "&lt;script&gt;alert(1)&lt;/script&gt;",
    "<a href='javascript:alert(1)'>x</a>",
]
# what a table of results may render to: the table itself, paragraphs and the bold of a title or a marker
ALLOWED_TAGS = {"table", "thead", "tbody", "tr", "th", "td", "p", "strong", "h1", "h2", "h3", "ul", "li", "em"}


def _html(md: str) -> list[str]:
    """The HTML of ``md`` by two renderers: markdown-it (CommonMark) and mistune with bare-URL autolinks (as GitHub)."""
    return [markdown_it.MarkdownIt("commonmark").enable("table").render(md),
            mistune.create_markdown(escape=False, plugins=["table", "url", "strikethrough"])(md)]


def _tags(html: str) -> set[str]:
    return {m.lower() for m in re.findall(r"</?([a-zA-Z][a-zA-Z0-9]*)", html)}


def _attributes(html: str) -> list[str]:
    """Every real tag that carries an attribute (escaped text such as ``&lt;a href=...`` is no tag)."""
    return re.findall(r"<[a-zA-Z][a-zA-Z0-9]*\s[^>]*>", html)


@pytest.mark.parametrize("text", HOSTILE)
def test_a_hostile_string_renders_as_text_in_keys_values_and_grids(text):
    results = {text: text, "grid": {text: {text: text, "R@1": 0.5}}, "list": [text, 1],
               "deeper": {"sweep": {text: {"0": text}}}}
    md = render_table(results)
    for html in _html(md):
        assert _tags(html) <= ALLOWED_TAGS, (text, _tags(html) - ALLOWED_TAGS, html)
        assert not _attributes(html), (text, _attributes(html))        # no href, src, onerror, style, ...
    assert "<" not in md and ">" not in md                 # pasted into HTML as it is, no tag either
    assert not re.search(r"(?i)\b(https?|javascript):|\bwww\.|@[\w-]+\.\w", md)   # nothing GitHub would autolink
    rows = [line for line in md.splitlines() if line.startswith("|")]
    assert all(len(re.findall(r"(?<!\\)\|", row)) == len(re.findall(r"(?<!\\)\|", rows[0])) for row in rows[:2])


def test_the_escaped_text_reads_as_what_was_recorded():
    """Escaping changes the Markdown, not what a reader sees."""
    for text in ["<b>R@1</b> (seed 0) [best] & `fast` | ok!", "https://example.org/x_y", "R@1.5 m"]:
        html = _html(render_table({"k": text}))[0]
        shown = re.sub(r"<[^>]+>", "", html)
        for entity, char in (("&lt;", "<"), ("&gt;", ">"), ("&quot;", '"'), ("&amp;", "&")):
            shown = shown.replace(entity, char)
        assert text in shown, (text, shown)


def test_the_existing_table_format_is_kept():
    assert escape_markdown("R@1") == "R@1" and escape_markdown("raw pixels") == "raw pixels"
    assert render_table({"name": "a|b"}).splitlines()[2] == "| name | a\\|b |"
    assert format_value(0.71234) == "0.712" and format_value([1, 5, 10]) == "1, 5, 10"


@pytest.mark.parametrize("value, shown", [
    (math.nan, "**⚠ NaN**"), (math.inf, "**⚠ inf**"), (-math.inf, "**⚠ -inf**"),
    ("nan", "**⚠ NaN**"), ("inf", "**⚠ inf**"), ("-inf", "**⚠ -inf**"),    # as record() stores them
    ([0.5, math.nan], "0.500, **⚠ NaN**"),
])
def test_a_non_finite_value_is_marked_not_printed_as_a_number(value, shown):
    assert format_value(value) == shown
    md = render_table({"R@1": value, "grid": {"T": {"R@1": value}}})
    assert md.count(shown) == 2
    assert "<strong>⚠" in _html(md)[0]
    assert "| R@1 | nan |" not in md and "| R@1 | inf |" not in md


def test_the_whole_report_has_no_link_or_image_but_its_own_figures():
    evil = "<img src=x onerror=alert(1)>[x](javascript:alert(1))"
    notebooks = [{"name": "00_ok", "status": "ok", "error": "", "seconds": 1.0, "figures": ["figures/00_ok_03_0.png"],
                  "results": {"00_ok": {evil: evil, "R@1": math.nan}, evil: {"a": "https://evil.example"}}},
                 {"name": "01_bad", "status": "failed", "error": f"RuntimeError: {evil}` ![](http://evil.example/i.png)",
                  "seconds": 2.0, "figures": [], "results": {}}]
    md = render_markdown({"git commit": evil, "profile": "ci"}, notebooks)
    for html in _html(md):
        tagged = _attributes(html)                  # the report's own figure is the only tag with an attribute
        assert len(tagged) == 1 and re.fullmatch(r'<img src="figures/00_ok_03_0\.png" alt="00_ok_03_0"\s*/?>',
                                                 tagged[0]), tagged
        assert _tags(html) <= ALLOWED_TAGS | {"img"}, _tags(html) - ALLOWED_TAGS
    assert "<" not in md and "**⚠ NaN**" in md and "**failed**" in md
