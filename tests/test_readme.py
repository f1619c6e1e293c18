"""The README is for the student first, and what it (and docs/) says about the notebooks can be counted.

Checked here: README's length; the two commands a student needs (``make venv``, ``make lab``) near its top;
its notebook table lists exactly the notebooks, in rows a newcomer can read; every relative link of README.md
and docs/*.md reaches a file (and a heading, when it names one); no placeholder or made-up address of the
project; and every number of exercises, hints, self-check questions and graded exercises it claims is the
number the notebooks hold."""
import json
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
STUDENT_COMMANDS = ("make venv", "make lab")
MAX_LINES, FIRST_LINES, FIRST_WORDS, ROW_WORDS = 200, 40, 300, 25
NUMBER_WORDS = {w: i for i, w in enumerate(
    "zero one two three four five six seven eight nine ten eleven twelve".split())}


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _prose(text: str) -> str:
    """The text without fenced code blocks and inline code spans, lines joined: what a claim is made in."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)
    return re.sub(r"\s+", " ", re.sub(r"`[^`\n]*`", "", text))


# --- what the notebooks hold --------------------------------------------------------------------------------

def _section_items(markdown: list[str], title: str) -> list[str]:
    """The numbered items of the notebook's ``## <title>`` section (as tests/test_student_text.py reads them)."""
    for src in markdown:
        if f"## {title}" in src:
            body = src.split(f"## {title}", 1)[1].split("\n## ", 1)[0]
            return [it for it in re.split(r"\n(?=\d+\. )", "\n" + body.strip()) if re.match(r"\d+\. ", it.strip())]
    return []


def _notebook_counts() -> dict[str, dict[str, int]]:
    """{"NN": {"exercises", "hinted", "self_checks", "graded"}} for every notebook."""
    counts = {}
    for path in NOTEBOOKS:
        cells = json.loads(_text(path))["cells"]
        markdown = ["".join(c["source"]) for c in cells if c["cell_type"] == "markdown"]
        exercises = _section_items(markdown, "Exercises")
        counts[path.name[:2]] = {
            "exercises": len(exercises),
            "hinted": sum("<details><summary>Hint</summary>" in it for it in exercises),
            "self_checks": len(_section_items(markdown, "Self-check")),
            "graded": sum(bool(c.get("metadata", {}).get("nbgrader", {}).get("solution")) for c in cells),
        }
    return counts


COUNTS = _notebook_counts()


def _number(word: str) -> int | None:
    return int(word) if word.isdigit() else NUMBER_WORDS.get(word.lower())


def _scope(first: str | None, last: str | None) -> list[str]:
    """The notebooks "notebooks NN–MM" names (all of them when no range is given)."""
    if first is None:
        return sorted(COUNTS)
    assert f"{first}" in COUNTS and f"{last}" in COUNTS, f"notebooks {first}–{last}: no such notebooks"
    return [nb for nb in sorted(COUNTS) if first <= nb <= last]


def _claims(text: str) -> list[tuple[str, int, int]]:
    """(the claim, the number it states, the number the notebooks hold) for each countable claim in ``text``."""
    prose = _prose(text)
    total = {key: sum(c[key] for c in COUNTS.values()) for key in ("exercises", "hinted", "self_checks", "graded")}
    found = []

    def add(match, stated, actual):
        if stated is not None:
            found.append((match.group(0), stated, actual))

    for m in re.finditer(r"\b(\w+) (ungraded |graded )?exercises in all", prose):
        add(m, _number(m.group(1)), total["graded" if m.group(2) == "graded " else "exercises"])
    for m in re.finditer(r"\b(\w+) exercises with a hint", prose):
        add(m, _number(m.group(1)), total["hinted"])
    for m in re.finditer(r"\b(\w+) self-check questions in all", prose):
        add(m, _number(m.group(1)), total["self_checks"])
    for m in re.finditer(r"[Nn]otebooks (\d\d)[–-](\d\d)\b[^.]*?\b(\w+) (self-check questions|graded exercises) each",
                         prose):
        key = "self_checks" if m.group(4).startswith("self") else "graded"
        stated = _number(m.group(3))
        for nb in _scope(m.group(1), m.group(2)):
            add(m, stated, COUNTS[nb][key])
    for m in re.finditer(r"(?:[Ii]n notebooks (\d\d)[–-](\d\d),? )?\b[Ee]very (?:ungraded )?exercise has a hint", prose):
        for nb in _scope(m.group(1), m.group(2)):       # "every exercise has a hint": the hinted ones are all
            add(m, COUNTS[nb]["exercises"], COUNTS[nb]["hinted"])
    for m in re.finditer(r"[Ee]very notebook (?:ends|closes) with (\w+) self-check questions", prose):
        for nb in _scope(None, None):
            add(m, _number(m.group(1)), COUNTS[nb]["self_checks"])
    for m in re.finditer(r"[Ee]very notebook (?:ends with|has) (?:a list of )?(?:ungraded )?exercises", prose):
        for nb in _scope(None, None):                   # at least one each
            add(m, 1, min(COUNTS[nb]["exercises"], 1))
    for m in re.finditer(r"\b(\d\d) and (\d\d) have no (hints|self-check questions)", prose):
        key = "hinted" if m.group(3) == "hints" else "self_checks"
        for nb in m.group(1, 2):
            add(m, 0, COUNTS[nb][key])
    return found


def test_the_notebooks_are_counted():
    assert len(COUNTS) >= 9, f"expected the course's notebooks in notebooks/, found {sorted(COUNTS)}"
    assert all(c["exercises"] for c in COUNTS.values()), f"a notebook without an ## Exercises list: {COUNTS}"


@pytest.mark.parametrize("path", [README, *DOCS], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_count_of_exercises_hints_and_self_checks_holds(path):
    wrong = [f"{claim!r}: says {stated}, the notebooks hold {actual}"
             for claim, stated, actual in _claims(_text(path)) if stated != actual]
    assert not wrong, f"{path.name} claims what the notebooks do not hold ({COUNTS}):\n" + "\n".join(wrong)


def test_readme_states_what_students_get_to_practise():
    claims = " ".join(claim for claim, _, _ in _claims(_text(README)))
    for what in ("exercises", "hint", "self-check"):
        assert what in claims, f"README must say, countably, how many {what} the notebooks have"


# --- the README's shape -------------------------------------------------------------------------------------

def test_readme_is_short():
    lines = _text(README).splitlines()
    assert len(lines) <= MAX_LINES, f"README.md has {len(lines)} lines; at most {MAX_LINES} (move detail to docs/)"


@pytest.mark.parametrize("command", STUDENT_COMMANDS)
def test_the_students_commands_come_first(command):
    lines = _text(README).splitlines()
    at = next((i for i, line in enumerate(lines) if re.search(rf"\b{command}\b", line)), None)
    assert at is not None, f"README.md never says `{command}`"
    words_before = sum(len(line.split()) for line in lines[:at])
    words_to = words_before + len(lines[at].split(command, 1)[0].split()) + len(command.split())
    assert at < FIRST_LINES, f"`{command}` first appears on line {at + 1}; it must be within the first {FIRST_LINES}"
    assert words_to <= FIRST_WORDS, f"`{command}` first appears after {words_to} words; at most {FIRST_WORDS}"


def _table_rows() -> list[list[str]]:
    """The cells of each row of README's notebook table (rows that name an ``NN_*.ipynb``)."""
    rows = []
    for line in _text(README).splitlines():
        if line.startswith("|") and re.search(r"\d\d_\w+\.ipynb", line):
            rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows


def test_the_notebook_table_lists_exactly_the_notebooks():
    listed = [re.search(r"\d\d_\w+\.ipynb", " ".join(row)).group(0) for row in _table_rows()]
    assert listed == [p.name for p in NOTEBOOKS], \
        f"README's notebook table lists {listed}; notebooks/ holds {[p.name for p in NOTEBOOKS]} (same order)"
    for row in _table_rows():
        number = row[0]
        name = re.search(r"\d\d_\w+\.ipynb", " ".join(row)).group(0)
        assert name.startswith(f"{number}_"), f"row {row}: its number is not its notebook's"


@pytest.mark.parametrize("row", _table_rows(), ids=lambda row: row[0])
def test_every_table_row_is_short(row):
    words = len(" ".join(row).replace("`", "").split())
    assert words <= ROW_WORDS, f"notebook {row[0]}'s row has {words} words; at most {ROW_WORDS}: {row}"


# --- links and addresses ------------------------------------------------------------------------------------

def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation (backticks included) dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", _text(path), flags=re.M | re.S)
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+?)\s*$", text, flags=re.M)}


def _links(path: Path) -> list[str]:
    text = re.sub(r"^```.*?^```", "", _text(path), flags=re.M | re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"\]\(([^)\s]+)\)", text)


@pytest.mark.parametrize("path", [README, *DOCS], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_reaches_a_file(path):
    broken = []
    for target in _links(path):
        if re.match(r"[a-z][a-z+.-]*:", target):        # https:, mailto: ...: not a file of the repository
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            broken.append(f"{target}: no {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: {dest.name} has no heading with the anchor #{anchor}")
    assert not broken, f"{path.relative_to(ROOT)}: broken links:\n" + "\n".join(broken)


def test_no_placeholder_or_invented_address_of_the_project():
    urls = tomllib.loads(_text(ROOT / "pyproject.toml"))["project"].get("urls", {})
    known = " ".join(urls.values())
    for path in [README, *DOCS]:
        text = _text(path)
        assert "OWNER/" not in text, f"{path.name}: an `OWNER/` placeholder where an address would be"
        for m in re.finditer(r"github\.com/([\w.-]+/vpr[-_]notebooks)\b|(?:mybinder\.org/v2/gh|"
                             r"colab\.research\.google\.com/github)/([\w.-]+/[\w.-]+)", text):
            assert (m.group(1) or m.group(2)) in known, (
                f"{path.name}: {m.group(0)} is an address of the project that pyproject.toml's [project.urls] "
                "does not hold (write it there once, or leave it out)")


def test_the_teachers_table_lists_every_graded_exercise():
    """docs/teaching.md's table of graded exercises: exactly the notebooks' nbgrader solution cells, in order."""
    listed = re.findall(r"^\| (\d\d) \| `(ex-[\w-]+)` \|", _text(ROOT / "docs" / "teaching.md"), flags=re.M)
    graded = []
    for path in NOTEBOOKS:
        for cell in json.loads(_text(path))["cells"]:
            nbgrader = cell.get("metadata", {}).get("nbgrader", {})
            if nbgrader.get("solution"):
                graded.append((path.name[:2], nbgrader["grade_id"]))
    assert listed == graded, f"docs/teaching.md lists {listed}; the notebooks grade {graded}"


def test_readme_quotes_the_pointer_the_error_messages_give():
    """The reproduction commands' error messages send a user to a page and a section ("see PAGE, 'SECTION'");
    README quotes that pointer: it must be the text the package prints, and the page must hold the section."""
    said = set()
    for path in sorted((ROOT / "vpr_nb").rglob("*.py")):
        said |= set(re.findall(r"\(see ([\w./-]+\.md, '[^']+')\)", _text(path)))
    assert len(said) == 1, f"the package's error messages point to {sorted(said) or 'no page'}; expected one pointer"
    pointer = said.pop()
    readme = re.sub(r"\s+", " ", _text(README))
    quoted = re.search(r"error messages point there as \"([^\"]+)\"", readme)
    assert quoted, "README no longer says where the reproduction commands' error messages point"
    assert quoted.group(1) == pointer, f"README says the messages point to {quoted.group(1)!r}; they say {pointer!r}"
    page, section = re.fullmatch(r"(.+), '(.+)'", pointer).groups()
    headings = re.findall(r"^#{1,6} (.+?)\s*$", _text(ROOT / page), flags=re.M)
    assert any(h.startswith(section) for h in headings), f"{page} has no section {section!r}: {headings}"
