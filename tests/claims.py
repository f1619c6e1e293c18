"""A claim checker for notebook prose: what a markdown sentence states against what the notebook prints.

:func:`check_notebook` reads a notebook's markdown cells sentence by sentence and checks three kinds of claim
against the notebook's stored outputs (stream text and ``text/plain`` of its code cells) and its committed
results (``notebooks/results/NN_*.json``). It returns :class:`Finding` objects; ``tests/test_claims.py`` runs it.

**Sentences.** Markdown cells without fenced code, tables and headings, split at ``. ! ?`` before a capital, at
blank lines and at list items. HTML tags are dropped; inline code and maths hold no checked number (maths still
names quantities: ``$p(0, 10)$``). A sentence right after ``<!-- claim: skip: REASON -->`` is not checked (the
escape hatch for a sentence this module misreads; the reason is required).

**Rule 1, numbers name their quantity.** The quantities this module knows (:data:`QUANTITIES`): ``R@N`` /
``Recall@N``, with ``val``/``validation`` just before it ``val R@N``; ``cosine`` (``cos``, ``mean cosine``);
``best epoch``; ``loss``; ``p(d1, d2)`` (the mis-ordering probability). A sentence number is *attached* to the
nearest quantity phrase before it in its clause (no ``;`` between, at most 8 words apart), else to one at most 3
words after it. Checked numbers: decimals (``0.602``, ``−0.020``), ``N %`` and ``N points`` (read as N/100), and
integers only when attached to ``best epoch``. Not checked: unattached numbers, numbers after "about",
"roughly", "around", "nearly", "almost", "~" or "≈", numbers right after a setting's name (``lr 0.5``,
``margin``, ``K``, ``seed``, ``α``...), numbers followed by a unit (``20 m``, ``3 epochs``), numbers of a clause that quotes a paper (from "paper" to the
end of its clause), references (``Eq. (4)``, ``Table II``, ``notebook 03``) and parts of names (``R@10``,
``NetVLAD-16``). An output number *occurs* with a label: in a table, the header cells above it (columns split
at two spaces, a cell overlapping the number's characters) plus the quantity phrase nearest before it on its own
line (all of the line's phrases when none precedes it). A committed result's label is its JSON key path; a list
of numbers also gives its mean. An attached number passes when one occurrence (at the precision written: within
half a unit of its last digit, signs ignored) has a label naming a compatible quantity (``R@1`` is compatible
with ``val R@1``, not the reverse). It is skipped when some occurrence's label names no quantity (the output does
not say what the number is). Otherwise (not found, or found only under other quantities) it is flagged. A sentence
naming ``notebook NN`` may also be backed by notebook NN's outputs and results.

**Rule 2, directions.** (a) A rise or fall word (``rose``, ``rises``, ``lifts``, ``climbs``... / ``fell``,
``falls``, ``drops``, ``lowers``, ``halves``...) followed within 8 words by ``from A ... to B`` or ``A → B``
claims B > A (rise) or B < A (fall). (b) A comparative (``higher``, ``larger``, ``above``, ``beats``, ``better``
/ ``lower``, ``smaller``, ``below``, ``worse``) before ``A vs B`` in the same clause claims A > B (or A < B);
``better``, ``beats``, ``worse`` are reversed for quantities where lower is better (``p(...)``, ``loss``). The
numbers are also checked by rule 1 when the clause names their quantity.

**Rule 3, verdicts.** The notebook prints verdicts (:mod:`vpr_nb.verdict`) as ``A − B: m ± s (n seeds, t .., Holm
p .. over k comparisons): helps`` (``hurts``, ``no measurable effect``), ``A − B, premise on: ...: helps``, ``A − B:
inconclusive: ...`` and ``control: A − B = ...: passes`` (``fails``); older notebooks' ``A is better`` / ``within
2 SE, no verdict`` / ``A vs B: inconclusive`` are read too. Each gives a winner (A, B or none). A
sentence claims one with (a) the printed form ``A − B[, premise on|off]: helps`` (``hurts``, ``no measurable
effect``, ``within 2 SE``, ``inconclusive``, ``X is better``), or (b) two printed names with a verb between
them: ``A beats B``, ``A is better than B``, ``A outperforms B``, ``A is above B`` (A wins), ``A trails B``,
``A is below B``, ``A loses to B`` (B wins), ``A vs B is within 2 SE`` / ``is inconclusive`` (none); ``not``
just before the verb negates it. The claim must agree with one printed verdict for that pair (a claim of no
winner agrees with "within 2 SE", "no measurable effect" and "inconclusive").

**Predictions are not claims:** a sentence marked ``**Prediction.**``, one that starts with "if", or one with "would"
or "falsify" states no outcome, so its direction and verdict words are skipped.

**What it cannot check:** numbers whose quantity the sentence does not name, or that no output labels
("0.451 of the queries"); words instead of numbers ("about one in seven", "halve"); comparisons written with
paraphrased names ("the layer alone", "random dense places"); sentences about papers, figures or what a reader
should do; whether a verdict's reason is right. A sentence it cannot parse is skipped, never failed.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
RESULTS = NOTEBOOKS / "results"


@dataclass(frozen=True)
class Finding:
    notebook: str
    cell: int
    rule: str          # "number", "direction", "verdict"
    sentence: str
    why: str

    def __str__(self):
        return f"{self.notebook} cell {self.cell} [{self.rule}] {self.why}\n    sentence: {self.sentence}"


# --- quantities -------------------------------------------------------------------------------------------

_MINUS = "−"
QUANTITIES = re.compile(
    r"(?P<val>\bval(?:idation)?\.?\s+)?(?<![\w-])(?:R|Recall)@(?P<n>\d+)\b"
    r"|(?P<cos>(?<![\w-])cos(?:ines?)?\b)"
    r"|(?P<epoch>\bbest\s+epochs?\b)"
    r"|(?P<loss>(?<![\w-])loss(?:es)?\b)"
    r"|(?P<p>(?<![\w\\])p\s*\(\s*(?P<d1>\d+(?:\.\d+)?)\s*(?:m\s*)?,\s*(?P<d2>\d+(?:\.\d+)?)\s*(?:m\s*)?\))", re.I)
LOWER_IS_BETTER = ("p(", "loss")


def quantity_phrases(text: str) -> list[tuple[int, int, str]]:
    """(start, end, key) of every quantity phrase of ``text``: keys ``R@1``, ``val R@1``, ``cosine``,
    ``best epoch``, ``loss``, ``p(0,10)``."""
    out = []
    for m in QUANTITIES.finditer(text):
        if m.group("n"):
            key = ("val " if m.group("val") else "") + f"R@{m.group('n')}"
        elif m.group("cos"):
            key = "cosine"
        elif m.group("epoch"):
            key = "best epoch"
        elif m.group("loss"):
            key = "loss"
        else:
            key = f"p({float(m.group('d1')):g},{float(m.group('d2')):g})"
        out.append((m.start(), m.end(), key))
    return out


def compatible(claimed: str, labelled: str) -> bool:
    """A sentence's quantity ``claimed`` is what an output labelled ``labelled`` shows (R@1 covers val R@1)."""
    return claimed == labelled or (claimed.startswith("R@") and labelled == "val " + claimed)


# --- outputs and committed results ------------------------------------------------------------------------

_OUT_NUMBER = re.compile(r"(?<![\w@.^/\\])(?<![A-Za-z]-)[-+−]?\d+(?:\.\d+)?(?![\w.]*[A-Za-z_])")


@dataclass(frozen=True)
class Occurrence:
    value: float
    keys: frozenset


def _cells(line: str) -> list[tuple[int, int]]:
    """Column cells of a printed table line: runs of text separated by two or more spaces."""
    return [(m.start(), m.end()) for m in re.finditer(r"\S+(?: \S+)*", line)]


def _line_keys(line: str, pos: int) -> set[str]:
    """The quantity named on ``line`` for a number at ``pos``: the nearest phrase before it, else all the line's."""
    phrases = quantity_phrases(line)
    before = [p for p in phrases if p[1] <= pos]
    return {before[-1][2]} if before else {p[2] for p in phrases}


def output_occurrences(text: str) -> list[Occurrence]:
    """Every number of a printed output with the quantities its line and the header cells above it name."""
    out = []
    lines = text.replace("\r", "").split("\n")
    for i, line in enumerate(lines):
        for m in _OUT_NUMBER.finditer(line):
            keys = _line_keys(line, m.start())
            for above in reversed(lines[:i]):            # header cells, up to the block's first line
                if not above.strip():
                    break
                for s, e in _cells(above):
                    cell = above[s:e]
                    if s < m.end() and m.start() < e and re.search(r"[A-Za-z]", cell):
                        keys |= {k for _, _, k in quantity_phrases(cell)}
            out.append(Occurrence(abs(float(m.group(0).replace(_MINUS, "-"))), frozenset(keys)))
    return out


def output_texts(nb: dict) -> list[str]:
    texts = []
    for cell in nb["cells"]:
        if cell["cell_type"] != "code":
            continue
        for o in cell.get("outputs", []):
            if o.get("output_type") == "stream":
                texts.append(_join(o.get("text", "")))
            plain = o.get("data", {}).get("text/plain")
            if plain and "image/png" not in o.get("data", {}):
                texts.append(_join(plain))
    return texts


def json_occurrences(value, path: tuple = ()) -> list[Occurrence]:
    """Every number of a committed result, labelled by its key path; a list of numbers also gives its mean."""
    keys = frozenset(k for _, _, k in quantity_phrases(" ".join(str(p) for p in path)))
    if isinstance(value, bool):
        return []
    if isinstance(value, (int, float)):
        return [Occurrence(abs(float(value)), keys)]
    if isinstance(value, dict):
        return [o for k, v in value.items() for o in json_occurrences(v, path + (k,))]
    if isinstance(value, list):
        out = [o for v in value for o in json_occurrences(v, path)]
        nums = [v for v in value if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if nums and len(nums) == len(value):
            out.append(Occurrence(abs(sum(nums) / len(nums)), keys))
        return out
    return []


def backing(nb: dict, number: str | None, results_dir: Path | None = RESULTS) -> list[Occurrence]:
    """The occurrences of notebook ``nb`` (number ``"02"``): its outputs and its committed results."""
    occ = [o for t in output_texts(nb) for o in output_occurrences(t)]
    if number and results_dir is not None:
        for path in sorted(Path(results_dir).glob(f"{number}_*.json")):
            occ += json_occurrences(json.loads(path.read_text(encoding="utf-8")).get("results", {}))
    return occ


# --- verdicts printed -------------------------------------------------------------------------------------

_PRINTED = re.compile(r"^\s*(?:(?P<metric>[^:−=\[]+?):\s+)?(?P<a>[^:−=\[]+?) − (?P<b>[^:=\[]+?)"
                      r"(?:, (?P<cond>premise (?:on|off)))?\s*(?:=|:)\s*[-+−]?\d[^:]*:\s*(?P<verdict>[^\[]+?)\s*(?:\[.*)?$")
_PRINTED_INCONCLUSIVE = re.compile(r"^\s*(?:(?P<metric>[^:]+?):\s+)?(?P<a>[^:]+?) (?:vs|−) (?P<b>[^:]+?): inconclusive")


@dataclass(frozen=True)
class Verdict:
    a: str
    b: str
    cond: str
    winner: str | None


def _winner_word(a: str, b: str, text: str) -> str | None | bool:
    """The winner a verdict text gives (a, b or None); False when the text is no verdict."""
    text = text.strip().rstrip(".").lower()
    if text.endswith(" is better"):
        name = text[: -len(" is better")].strip()
        return a if name == a.lower() else b if name == b.lower() else False
    if text.startswith(("helps", "passes")):
        return a
    if text.startswith("hurts"):
        return b
    if text.startswith(("no measurable effect", "within 2 se", "inconclusive", "fails", "no verdict")) \
            or "no verdict" in text:
        return None
    return False


def printed_verdicts(nb: dict) -> list[Verdict]:
    found = []
    for text in output_texts(nb):
        for line in text.splitlines():
            m = _PRINTED.match(line)
            if m:
                a, b = m.group("a").strip(), m.group("b").strip()
                winner = _winner_word(a, b, m.group("verdict"))
                if winner is not False:
                    found.append(Verdict(a, b, m.group("cond") or "", winner))
                continue
            m = _PRINTED_INCONCLUSIVE.match(line)
            if m:
                found.append(Verdict(m.group("a").strip(), m.group("b").strip(), "", None))
    return found


# --- sentences --------------------------------------------------------------------------------------------

_ABBREVIATION = re.compile(r"(?:\b(?:Eqs?|Figs?|Sec|Secs|vs|cf|approx|No)|\be\.g|\bi\.e|\bet al)\.$")
_SKIP_MARK = re.compile(r"<!--\s*claim:\s*skip:\s*\S[^>]*-->")


def _join(src) -> str:
    return src if isinstance(src, str) else "".join(src)


def sentences(markdown: str) -> list[tuple[str, bool]]:
    """(sentence, skipped) of a markdown cell: headings, tables and fenced code dropped, HTML tags removed;
    ``skipped`` when the escape-hatch comment precedes it."""
    text = re.sub(r"```.*?```", " ", markdown, flags=re.S)
    text = _SKIP_MARK.sub(" CLAIMSKIP ", text)
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    text = re.sub(r"</?[A-Za-z][^>]*>", " ", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith(("#", "|"))]
    parts = []
    for part in re.split(r"(?<=[.!?])\s+(?=[A-Z0-9*(\"'`$])|(\n\s*\n|\n\s*(?:[*-]|\d+\.)\s+)", "\n".join(lines)):
        if part is None:
            continue
        if parts and parts[-1] is not None and _ABBREVIATION.search(parts[-1]) and not part.startswith("\n"):
            parts[-1] += " " + part                         # 'Eq. (4)', 'e.g. the', 'vs. B': not a sentence end
        else:
            parts.append(part)
    out = []
    skip_next = False
    for part in parts:
        part = re.sub(r"^(?:[*-]|\d+\.)\s+", "", " ".join(part.split()))
        if re.fullmatch(r"(?:[*-]|\d+\.)?", part):
            continue                                        # a list marker or a blank line
        if "CLAIMSKIP" in part:
            rest = part.replace("CLAIMSKIP", "").strip()
            if rest:
                out.append((rest, True))
            else:
                skip_next = True
            continue
        if part:
            out.append((part, skip_next))
            skip_next = False
    return out


_CODE = re.compile(r"`[^`]*`")
_MATH = re.compile(r"\$\$.*?\$\$|\$[^$]*\$", re.S)
_REFERENCE = re.compile(
    r"\b(?:eqs?\.|equations?|figs?\.|figures?|tables?|exercises?|secs?\.|sections?|notebooks?|steps?)"
    r"\s*\(?\d+\)?(?:\s*(?:[–-]|,|and|or|to)\s*\(?\d+\)?)*", re.I)
_PAPER = re.compile(r"\bpapers?(?:'s)?\b:?.*?(?=[;:)]|,\s+(?:and|but|not|so|where|while)\b|\.(?:\s|$)|$)", re.I)
_NUMBER = re.compile(r"(?<![\w@^/\\.-])([-+−]?)(\d+)(\.\d+)?(\s?%|\s+points?\b)?(?![\w.]*[A-Za-z_])")
_HEDGE = re.compile(r"(?:\babout|\broughly|\baround|\bnearly|\balmost|~|≈)\s*$", re.I)
_SETTING = re.compile(r"(?:\b(?:lr|learning rate|margin|alpha|K|M|seeds?|(?<!best )epochs?|radius|momentum|decay|"
                      r"temperature|width|size|[pk])|[ατσ])\s*(?:=|of|is)?\s*$")
_UNIT = re.compile(r"\s*(?:m|km|px|s|min|°|deg|epochs?|seeds?|queries|images|frames?|places|steps)\b")


def _blank(pattern: re.Pattern, text: str) -> str:
    return pattern.sub(lambda m: " " * len(m.group(0)), text)


@dataclass(frozen=True)
class Stated:
    start: int
    end: int
    value: float       # absolute value, as a fraction for % and points
    decimals: int      # of ``value``
    written: str


def stated_numbers(sentence: str) -> list[Stated]:
    """The checkable numbers of a sentence (see the module's rule 1), in order."""
    text = sentence.replace("**", "  ").replace("*", " ").replace("_", " ")
    for pattern in (_CODE, _MATH, _REFERENCE, _PAPER):
        text = _blank(pattern, text)
    out = []
    for m in _NUMBER.finditer(text):
        whole, frac, unit = m.group(2), m.group(3) or "", (m.group(4) or "").strip()
        if _HEDGE.search(text[: m.start()]) or _SETTING.search(text[: m.start()]) or _UNIT.match(text, m.end()):
            continue
        decimals = len(frac) - 1 if frac else 0
        value = float(whole + frac)
        if unit:
            value, decimals = value / 100, decimals + 2
        out.append(Stated(m.start(), m.end(), value, decimals, m.group(0).strip()))
    return out


def _clause_words(text: str, a: int, b: int) -> tuple[int, bool]:
    """Words between positions a < b of ``text``, and whether a clause break (``;``) lies between."""
    between = text[a:b]
    return len(re.findall(r"[\w$@.()±+−-]+", between)), ";" in between


def attach(sentence: str, number: Stated) -> str | None:
    """The quantity a number is attached to: the nearest phrase before it (8 words, same clause), else after (3)."""
    phrases = quantity_phrases(sentence)
    best = None
    for s, e, key in phrases:
        if e <= number.start:
            words, cut = _clause_words(sentence, e, number.start)
            if not cut and words <= 8 and (best is None or s > best[0]):
                best = (s, key)
    if best:
        return best[1]
    for s, e, key in phrases:
        if s >= number.end:
            words, cut = _clause_words(sentence, number.end, s)
            if not cut and words <= 3:
                return key
    return None


def _rounds_to(stated: Stated, value: float) -> bool:
    return abs(value - stated.value) <= 0.5 * 10.0 ** -stated.decimals + 1e-9


def number_verdict(stated: Stated, key: str, occurrences: list[Occurrence]) -> str:
    """'pass', 'skip' (an occurrence is unlabelled) or 'flag' for a number attached to quantity ``key``."""
    found = [o for o in occurrences if _rounds_to(stated, o.value)]
    if any(any(compatible(key, k) for k in o.keys) for o in found):
        return "pass"
    if any(not o.keys for o in found):
        return "skip"
    return "flag"


# --- rules ------------------------------------------------------------------------------------------------

_UP = r"ris(?:e|es|en|ing)|rose|increas(?:e|es|ed)|grow(?:s|n)?|grew|climb(?:s|ed)?|lift(?:s|ed)?|rais(?:e|es|ed)|doubl(?:e|es|ed)"
_DOWN = (r"fall(?:s|en)?|fell|drop(?:s|ped)?|decreas(?:e|es|ed)|declin(?:e|es|ed)|lower(?:s|ed)|shrink(?:s)?|shrank"
         r"|halv(?:e|es|ed)|cut(?:s)?")
_MOVE = re.compile(rf"\b(?:(?P<up>{_UP})|(?P<down>{_DOWN}))\b", re.I)
_COMPARE = re.compile(r"\b(?:(?P<up>higher|larger|greater|above|exceeds?)|(?P<down>lower|smaller|below)"
                      r"|(?P<good>better|beats?|outperforms?)|(?P<bad>worse|trails?))\b", re.I)


def _numbers_between(numbers: list[Stated], a: int, b: int) -> list[Stated]:
    return [n for n in numbers if a <= n.start and n.end <= b]


@dataclass(frozen=True)
class Claim:
    """A direction or verdict a sentence states, and whether the outputs agree with it."""
    rule: str
    said: str
    ok: bool
    why: str = ""


def direction_claims(sentence: str, numbers: list[Stated]) -> list[Claim]:
    """Rule 2: every direction a sentence states between two of its numbers, checked against their order."""
    found = []
    text = _blank(_MATH, _blank(_CODE, sentence))
    for m in _MOVE.finditer(text):
        window = text[m.end():]
        pair = re.search(r"\bfrom\s+\S+(?:\s*\([^)]*\))?\s+to\s+\S+|\S+\s*(?:→|->)\s*\S+", window)
        if not pair or len(window[:pair.start()].split()) > 8 or ";" in window[:pair.start()]:
            continue
        inside = _numbers_between(numbers, m.end() + pair.start(), m.end() + pair.end())
        if len(inside) != 2:
            continue
        a, b = inside
        up = bool(m.group("up"))
        said = f"'{m.group(0)}': {b.written} {'>' if up else '<'} {a.written}"
        found.append(Claim("direction", said, (b.value > a.value) if up else (b.value < a.value)))
    for m in re.finditer(r"\S+\s+(?:vs\.?|versus)\s+\S+", text):
        inside = _numbers_between(numbers, m.start(), m.end())
        if len(inside) != 2:
            continue
        clause_start = max(text.rfind(";", 0, m.start()), text.rfind(". ", 0, m.start()), -1) + 1
        words = list(_COMPARE.finditer(text, clause_start, m.start()))
        if not words:
            continue
        c, (a, b) = words[-1], inside
        greater = bool(c.group("up") or c.group("good"))
        if (c.group("good") or c.group("bad")) and (attach(sentence, a) or "").startswith(LOWER_IS_BETTER):
            greater = not greater
        said = f"'{c.group(0)}': {a.written} {'>' if greater else '<'} {b.written}"
        found.append(Claim("direction", said, (a.value > b.value) if greater else (a.value < b.value)))
    return found


_CLAIM_WORDS = (r"helps?|hurts?|no measurable effect|within 2 SE|inconclusive|no verdict|[^;:.]+? is better")
_WIN_VERBS = re.compile(r"^\s*(?:(?P<neg>does not|do not|doesn't|don't|is not|isn't|not|never)\s+)?"
                        r"(?:(?P<a>beats?|outperforms?|(?:is |are |ends? )?(?:better than|above|ahead of))"
                        r"|(?P<b>trails?|loses? to|(?:is |are |ends? )?(?:worse than|below))"
                        r"|(?P<none>(?:is |are )?(?:within 2 SE|inconclusive|level with)))\s*$", re.I)


def _name_pattern(name: str) -> str:
    return r"(?<![\w-])" + re.escape(name).replace(r"\ ", r"\s+") + r"(?![\w-])"


def verdict_claims(sentence: str, verdicts: list[Verdict]) -> list[Claim]:
    """Rule 3: every verdict a sentence states on a printed pair, checked against the printed verdicts."""
    if not verdicts:
        return []
    text = re.sub(r"[*_]", "", sentence)
    claims = []                                              # (a, b, cond, winner, negated)
    pairs = {(v.a, v.b) for v in verdicts}
    for a, b in pairs:                                       # (a) the printed form, A − B[, premise on]: verdict
        pat = _name_pattern(a) + r"\s*[−-]\s*" + _name_pattern(b)
        for m in re.finditer(pat + rf"(?:,\s*(?P<cond>premise (?:on|off)))?\s*:\s*(?P<v>{_CLAIM_WORDS})", text, re.I):
            winner = _winner_word(a, b, m.group("v"))
            if winner is not False:
                claims.append((a, b, m.group("cond") or "", winner, False))
            rest = text[m.end():]
            for more in re.finditer(rf"[;,]\s*(?P<cond>premise (?:on|off))\s*:\s*(?P<v>{_CLAIM_WORDS})", rest, re.I):
                winner = _winner_word(a, b, more.group("v"))
                if winner is not False:
                    claims.append((a, b, more.group("cond"), winner, False))
    names = sorted({n for p in pairs for n in p}, key=len, reverse=True)
    spans = []                                               # (b) two printed names with a verb between them
    for name in names:
        for m in re.finditer(_name_pattern(name), text, re.I):
            if not any(s <= m.start() < e for s, e, _ in spans):
                spans.append((m.start(), m.end(), name))
    spans.sort()
    for (s1, e1, n1), (s2, e2, n2) in zip(spans, spans[1:]):
        between = text[e1:s2]
        if (n1, n2) not in pairs and (n2, n1) not in pairs or ";" in between:
            continue
        if re.fullmatch(r"\s*(?:vs\.?|versus)\s*", between):        # 'A vs B is within 2 SE'
            between = re.split(r"[;.(]", text[e2:])[0]
            m = _WIN_VERBS.match(between)
            if m and not m.group("none"):
                continue
        else:
            m = _WIN_VERBS.match(between)
        if not m:
            continue
        winner = n1 if m.group("a") else n2 if m.group("b") else None
        claims.append((n1, n2, "", winner, bool(m.group("neg"))))
    found = []
    for a, b, cond, winner, negated in claims:
        same = [v for v in verdicts if {v.a, v.b} == {a, b} and (not cond or v.cond == cond)]
        if not same:
            continue
        said = (f"{a} vs {b}{', ' + cond if cond else ''}: " + ("not " if negated else "")
                + (f"{winner} wins" if winner else "no winner"))
        printed = "; ".join(f"{v.a} − {v.b}{', ' + v.cond if v.cond else ''}: "
                            f"{(v.winner + ' wins') if v.winner else 'no winner'}" for v in same)
        ok = any((v.winner != winner) if negated else (v.winner == winner) for v in same)
        found.append(Claim("verdict", said, ok, f"printed: {printed}"))
    return found


def check_notebook(nb: dict, name: str = "notebook", number: str | None = None,
                   results_dir: Path | None = RESULTS, others: dict | None = None) -> list[Finding]:
    """Every claim of ``nb``'s markdown that its outputs contradict. ``number`` (``"02"``) picks the committed
    results; ``others`` maps a notebook number to its notebook dict, for sentences that name another notebook."""
    own = backing(nb, number, results_dir)
    verdicts = printed_verdicts(nb)
    findings = []
    for index, cell in enumerate(nb["cells"]):
        if cell["cell_type"] != "markdown":
            continue
        for sentence, skipped in sentences(_join(cell["source"])):
            if skipped:
                continue
            occurrences = own
            for ref in re.findall(r"\bnotebooks?\s+(\d\d(?:\s*(?:,|and|–|-)\s*\d\d)*)", sentence, re.I):
                for other in re.findall(r"\d\d", ref):
                    if others and other in others and other != number:
                        occurrences = occurrences + backing(others[other], other, results_dir)
            numbers = stated_numbers(sentence)
            for stated in numbers:
                key = attach(sentence, stated)
                if key is None or ("." not in stated.written and "%" not in stated.written
                                   and "point" not in stated.written and key != "best epoch"):
                    continue
                if number_verdict(stated, key, occurrences) == "flag":
                    findings.append(Finding(name, index, "number", sentence,
                                            f"{stated.written} ({key}) is in no output about {key}"))
            if _HYPOTHETICAL.search(sentence):        # a prediction or a condition states no outcome
                continue
            for claim in direction_claims(sentence, numbers) + verdict_claims(sentence, verdicts):
                if not claim.ok:
                    findings.append(Finding(name, index, claim.rule, sentence,
                                            f"claims {claim.said}" + (f"; {claim.why}" if claim.why else "")))
    return findings


# A sentence that predicts or supposes (a notebook states its prediction before its results) claims no outcome:
# its direction and verdict words are not checked (its numbers still are).
_HYPOTHETICAL = re.compile(r"\*\*Prediction\.\*\*|^\W*(?:if|suppose)\b|\bwould\b|\bfalsif", re.I)


def check_path(path: Path) -> list[Finding]:
    """:func:`check_notebook` on a stored notebook, with the course's other notebooks for cross-references."""
    others = {p.name[:2]: json.loads(p.read_text(encoding="utf-8"))
              for p in sorted(Path(path).parent.glob("[0-9][0-9]_*.ipynb"))}
    nb = json.loads(Path(path).read_text(encoding="utf-8"))
    return check_notebook(nb, Path(path).name, Path(path).name[:2], RESULTS, others)


if __name__ == "__main__":
    for notebook in sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb")):
        for finding in check_path(notebook):
            print(finding)
