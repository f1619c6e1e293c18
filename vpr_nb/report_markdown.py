"""The report's Markdown: recorded results as tables, every recorded string and key escaped so that no tag, link,
image or table cell can come from a result (:mod:`vpr_nb.report` writes ``results.md`` with it)."""
from __future__ import annotations

import math
import re
from collections.abc import Mapping

# Recorded strings and keys are text, never markup: ``&``, ``<`` and ``>`` become HTML entities (no tag, in
# Markdown or pasted into HTML), the Markdown punctuation that makes links, images, code and table cells is
# backslash-escaped (``\\`` first, so that a trailing backslash cannot undo an escape), and the colon of a URL
# scheme, the dot of ``www.`` and the ``@`` of an e-mail address become numeric references, so that no renderer
# turns them into an autolink (GitHub links bare ``https://…``, ``www.…`` and ``a@b.c``).
_MARKUP = str.maketrans({"\\": "\\\\", "&": "&amp;", "<": "&lt;", ">": "&gt;", "[": "\\[", "]": "\\]",
                         "(": "\\(", ")": "\\)", "!": "\\!", "`": "\\`", "|": "\\|", "\n": " ", "\r": " "})
_AUTOLINK = re.compile(r"(?i)(?<![a-z0-9+.-])(?:https?|ftp|javascript|vbscript|data|file|mailto|xmpp):"
                       r"|(?<![a-z0-9])www\.|@(?=[\w+-]+\.[\w-])")
_REFERENCE = {":": "&#58;", ".": "&#46;", "@": "&#64;"}
# A value that is not a finite number, shown so that it cannot pass for one: record() stores NaN / ±inf as the
# strings "nan" / "inf" / "-inf" (JSON has no such numbers); a float passed to render_table directly is NaN / inf.
NON_FINITE = {"nan": "**⚠ NaN**", "inf": "**⚠ inf**", "+inf": "**⚠ inf**", "-inf": "**⚠ -inf**",
              "infinity": "**⚠ inf**", "+infinity": "**⚠ inf**", "-infinity": "**⚠ -inf**"}


def escape_markdown(text) -> str:
    """``text`` (any recorded string or key) as literal Markdown and HTML: no tag, link, image, code span,
    autolink or table cell boundary can come from it; a newline becomes a space."""
    text = str(text).translate(_MARKUP)
    return _AUTOLINK.sub(lambda m: m.group(0)[:-1] + _REFERENCE[m.group(0)[-1]], text)


def format_value(value) -> str:
    """One table cell: floats to 3 decimals (3 significant digits when tiny), lists comma-joined, dicts as
    ``{key: value, ...}``, strings escaped (:func:`escape_markdown`).

    A value that is not a finite number (a float NaN / ±inf, or the strings ``"nan"`` / ``"inf"`` / ``"-inf"``
    that :func:`record` stores for them) is shown in bold with a warning sign: ``**⚠ NaN**``, ``**⚠ inf**``,
    ``**⚠ -inf**`` (:data:`NON_FINITE`)."""
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return NON_FINITE[str(value)]
        return f"{value:.3f}" if value == 0 or abs(value) >= 1e-3 else f"{value:.3g}"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, (list, tuple)):
        return ", ".join(format_value(v) for v in value)
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{escape_markdown(k)}: {format_value(v)}" for k, v in value.items()) + "}"
    text = str(value)
    return NON_FINITE.get(text.strip().lower()) or escape_markdown(text)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def render_table(results: Mapping) -> str:
    """Recorded results as Markdown.

    A flat dict becomes a two-column table (``name | value``); a dict of dicts becomes one table
    with the outer keys as rows and the union of the inner keys as columns (blank where missing);
    lists are comma-joined. A dict mixing both gives the flat table followed by the grid; a value
    that is itself a dict of dicts gets its own grid below, titled with its key. Keys and strings are
    escaped (:func:`escape_markdown`: no tag, link or image can come from a recorded result), and a value that
    is not a finite number is marked ``**⚠ NaN**`` / ``**⚠ inf**`` (:func:`format_value`).
    """
    if not isinstance(results, Mapping) or not results:
        raise ValueError("render_table() needs a non-empty dict, e.g. {'R@1': 0.71}")
    flat = {k: v for k, v in results.items() if not isinstance(v, Mapping)}
    deeper = {k: v for k, v in results.items() if isinstance(v, Mapping) and v
              and any(isinstance(x, Mapping) for x in v.values())}
    nested = {k: v for k, v in results.items() if isinstance(v, Mapping) and k not in deeper}
    parts = []
    if flat:
        parts.append(_table(["name", "value"], [[escape_markdown(k), format_value(v)] for k, v in flat.items()]))
    if nested:
        columns: list[str] = []
        for inner in nested.values():
            columns += [c for c in inner if c not in columns]
        rows = [[escape_markdown(k)] + [format_value(inner[c]) if c in inner else "" for c in columns]
                for k, inner in nested.items()]
        parts.append(_table([""] + [escape_markdown(c) for c in columns], rows))
    parts += [f"**{escape_markdown(k)}**\n\n{render_table(v)}" for k, v in deeper.items()]
    return "\n\n".join(parts)
