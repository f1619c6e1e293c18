"""The course site's own Sphinx extension (loaded by docs/site/conf.py).

* **Links to repository files.** README.md and docs/*.md link to files that are not pages of the site
  (``LICENSE``, ``binder/``, ``Makefile``, a module of ``vpr_nb``). Such a link becomes a link to the file in
  the repository when ``[project.urls] Repository`` is known, and plain text otherwise; a link to a file that
  does not exist in the repository either stays as it is, so MyST's "cross-reference target not found"
  warning fails the build (warnings are errors).
* **Notebook names.** A notebook's file name written as code (README's table of the notebooks) links to its page.
* **Widget cells.** A code cell that shows an interactive widget (the course's ``# (an interactive widget``
  comment, or ipywidgets in its source) gets a note: the page shows the output stored for the default state,
  and the sliders need a kernel (a launch button, or the notebook in Jupyter).
* **Commands.** ``.. command-help:: vpr_nb.train`` inserts what ``python -m vpr_nb.train --help`` prints,
  run at build time (80 columns), so the page cannot drift from the code.
* **Docstrings that are not reStructuredText.** The package's docstrings are written for ``help()`` and must also
  parse as reST. A block of one that does not (a ``|x|`` read as a substitution, a table wider than its border)
  is shown as written, in a literal block, so the page still renders, and the build warns naming the docstring:
  with ``-W`` the build fails until the docstring is fixed.
* **MathJax without a CDN.** The files of MathJax 3.2.2 that the pages use are copied from the
  ``sphinx-mathjax-offline`` package into ``_static/mathjax/`` (``mathjax_path`` points there).
* **index.html** redirects to README.html, the home page.
"""
from __future__ import annotations

import io
import os
import re
import shutil
import subprocess
import sys
from importlib.util import find_spec
from pathlib import Path, PurePosixPath
from urllib.parse import urlsplit

from docutils import nodes
from docutils.frontend import get_default_settings
from docutils.parsers.rst import Directive, Parser, directives, roles
from docutils.utils import new_document
from sphinx import addnodes
from sphinx.application import Sphinx
from sphinx.transforms import SphinxTransform
from sphinx.transforms.post_transforms import SphinxPostTransform
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective

LOGGER = logging.getLogger("vpr_site")

MATHJAX_SCRIPT = "mathjax/tex-chtml.js"       # relative to _static/
# what tex-chtml.js loads: the CHTML fonts, TeX extensions on demand (autoload), the menu and its a11y parts
MATHJAX_PARTS = ("tex-chtml.js", "output/chtml", "input/tex", "ui", "a11y", "sre", "adaptors")
MATHJAX_PACKAGE = "sphinx-mathjax-offline"   # PyPI: MathJax 3.2.2's files (Apache-2.0), no code of ours runs
WIDGET_CELL = re.compile(r"#\s*\(an interactive widget|\bipywidgets\b|\binteract(?:ive)?\(")
WIDGET_NOTE = ("Interactive widget. In Jupyter this cell shows sliders that redraw its output; a web page has "
               "no kernel, so what follows is the output stored for the default settings. To move the sliders, "
               "open the notebook in Jupyter ({how}).")
HELP_COLUMNS = "80"
HELP_TIMEOUT_S = 120


# --- the repository's address: pyproject.toml's [project.urls] Repository, nowhere else ---------------------------

def repository_url(pyproject: dict) -> str | None:
    """``[project.urls] Repository`` (https://github.com/ORG/REPO), or None when it is not set."""
    urls = pyproject.get("project", {}).get("urls", {}) or {}
    url = next((v for k, v in urls.items() if k.strip().lower() == "repository"), None)
    return url.strip().rstrip("/").removesuffix(".git") if url and url.strip() else None


def package_version(root: Path) -> str:
    """vpr_nb.__version__, read from the source (the version string lives there only)."""
    text = (root / "vpr_nb" / "__init__.py").read_text(encoding="utf-8") if (root / "vpr_nb").is_dir() else ""
    m = re.search(r'^__version__\s*=\s*"([^"]+)"', text, flags=re.M)
    return m.group(1) if m else ""


def launch_options(repository: str | None, branch: str) -> dict:
    """sphinx-book-theme options: Binder and Colab buttons on notebook pages, only when the address is known."""
    if not repository:
        return {}
    options = {"repository_url": repository, "repository_branch": branch, "path_to_docs": "",
               "use_repository_button": True,
               "launch_buttons": {"binderhub_url": "https://mybinder.org", "notebook_interface": "jupyterlab"}}
    if urlsplit(repository).netloc.lower() == "github.com":          # Colab opens notebooks from GitHub only
        options["launch_buttons"]["colab_url"] = "https://colab.research.google.com"
    return options


# --- links to files of the repository that are not pages ------------------------------------------------------------

def _repo_path(docname: str, target: str) -> str | None:
    """The repository-relative path a relative link of ``docname`` points to (None for a URL or an anchor)."""
    path = target.split("#", 1)[0]
    if not path or re.match(r"[a-z][a-z0-9+.-]*:", path):
        return None
    joined = os.path.normpath(os.path.join(os.path.dirname(docname), path)).replace(os.sep, "/")
    return None if joined.startswith("..") else joined


class RepositoryFileLinks(SphinxPostTransform):
    """Turn a MyST link to a repository file that is not a page into a repository link or plain text."""

    default_priority = 5          # before myst-parser's resolver (priority 9), which would warn

    def run(self, **kwargs) -> None:
        root = Path(self.config.vpr_site_root)
        repo, branch = self.config.vpr_site_repository, self.config.vpr_site_branch
        for node in list(self.document.findall(addnodes.pending_xref)):
            if node.get("reftype") != "myst" or node.get("refdomain") not in (None, ""):
                continue
            rel = _repo_path(node.get("refdoc", self.env.docname), node["reftarget"])
            if rel is None or not (root / rel).exists():
                continue                     # not a repository file: MyST resolves it, or warns
            text = node.astext() or rel
            if repo:
                kind = "tree" if (root / rel).is_dir() else "blob"
                new = nodes.reference("", "", nodes.literal(text, text) if not node.astext() else
                                      nodes.inline(text, text), refuri=f"{repo}/{kind}/{branch}/{rel}",
                                      classes=["repository-file"], reftitle=f"{rel} in the repository")
            else:
                new = nodes.inline("", "", *(node.children or [nodes.literal(text, text)]),
                                   classes=["repository-file"])
                new["title"] = f"{rel}: a file of the repository, not a page of this site"
            node.replace_self(new)


class NotebookNameLinks(SphinxPostTransform):
    """A notebook's file name in code (README's table: ``00_synthetic_world.ipynb``) links to its page."""

    default_priority = 20
    formats = ("html",)

    def run(self, **kwargs) -> None:
        for literal in list(self.document.findall(nodes.literal)):
            m = _NOTEBOOK_NAME.fullmatch(literal.astext().strip())
            target = f"notebooks/{m.group(1)}" if m else None
            if target is None or target not in self.env.all_docs or target == self.env.docname:
                continue
            if any(isinstance(a, (nodes.reference, addnodes.pending_xref)) for a in _ancestors(literal)):
                continue
            uri = self.app.builder.get_relative_uri(self.env.docname, target)
            literal.replace_self(nodes.reference("", "", literal.deepcopy(), refuri=uri, internal=True))


_NOTEBOOK_NAME = re.compile(r"(?:notebooks/)?(\d\d_\w+)\.ipynb")


def _ancestors(node: nodes.Node):
    while node.parent is not None:
        node = node.parent
        yield node


# --- widget cells: a note on the static output ------------------------------------------------------------------------

class WidgetNotes(SphinxTransform):
    """Put a note at the top of every notebook code cell that shows an interactive widget."""

    default_priority = 900

    def apply(self, **kwargs) -> None:
        if not str(self.env.doc2path(self.env.docname)).endswith(".ipynb"):
            return
        how = ("the Binder or Colab button at the top of this page, or `make lab` in a clone"
               if self.config.vpr_site_repository else "`make lab` in a clone of the repository")
        for cell in list(self.document.findall(nodes.container)):
            if cell.get("nb_element") != "cell_code":
                continue
            source = "".join(n.astext() for n in cell.findall(nodes.literal_block)
                             if n.parent.get("nb_element") == "cell_code_source")
            if not WIDGET_CELL.search(source):
                continue
            text = WIDGET_NOTE.format(how=how)
            para = nodes.paragraph()
            for i, part in enumerate(text.split("`")):
                para += nodes.literal(part, part) if i % 2 else nodes.Text(part)
            note = nodes.note("", para, classes=["widget-note"])
            cell.insert(0, note)


# --- docstrings that are not reST: shown as written -------------------------------------------------------------------

# The trial parse is plain docutils: any directive and any role is accepted (Sphinx's own, napoleon's fields and
# rubrics), a directive's content is parsed as reST unless it is code or maths, and a role's text is a literal.
_OPAQUE_DIRECTIVES = {"math", "code-block", "code", "sourcecode", "literalinclude", "raw", "parsed-literal",
                      "highlight", "doctest", "testcode", "testoutput", "graphviz"}


_SPHINX_SUBSTITUTIONS = {"version", "release", "today", "translation progress"}


class _AnyDirective(Directive):
    optional_arguments = 100
    final_argument_whitespace = True
    has_content = True

    def run(self) -> list[nodes.Node]:
        node = nodes.container()
        if self.name not in _OPAQUE_DIRECTIVES:
            self.state.nested_parse(self.content, self.content_offset, node)
        return [node]


def _any_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    return [nodes.literal(rawtext, text)], []


def rest_problems(lines: list[str]) -> list[tuple[int | None, str]]:
    """(line, message) of each docutils warning or error of ``lines`` parsed alone (any directive or role allowed).

    The line counts from 1; it is None for an undefined substitution (``|x|`` meant as an absolute value).
    """
    settings = get_default_settings(Parser)
    settings.report_level, settings.halt_level, settings.warning_stream = 5, 5, io.StringIO()
    document = new_document("<docstring>", settings)
    problems: list[tuple[int | None, str]] = []

    def observe(msg: nodes.system_message) -> None:
        if msg["level"] >= 2:
            text = msg.children[0].astext() if msg.children else msg.astext()
            problems.append((msg.get("line"), text.strip().splitlines()[0]))

    document.reporter.attach_observer(observe)
    lookups = directives.directive, roles.role
    directives.directive = lambda name, language, document: (_AnyDirective, [])
    roles.role = lambda name, language, lineno, reporter: (_any_role, [])
    try:
        Parser().parse("\n".join(lines), document)
    finally:
        directives.directive, roles.role = lookups
    # substitutions are resolved by a transform, after parsing: check them here
    problems += [(None, f"Undefined substitution referenced: |{ref['refname']}|")
                 for ref in document.findall(nodes.substitution_reference)
                 if ref["refname"] not in document.substitution_defs and ref["refname"] not in _SPHINX_SUBSTITUTIONS]
    return problems


def _chunks(lines: list[str]) -> list[tuple[int, int]]:
    """[start, end) of each top-level block: text from an unindented line after a blank one to the next such line."""
    chunks: list[tuple[int, int]] = []
    start = last = None
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        if start is None:
            start = i
        elif not lines[i - 1].strip() and not line[:1].isspace():
            chunks.append((start, last + 1))
            start = i
        last = i
    if start is not None:
        chunks.append((start, last + 1))
    return chunks


def _literal(block: list[str]) -> list[str]:
    return ["", ".. code-block:: text", "", *(f"   {line}" if line.strip() else "" for line in block), ""]


def as_valid_rest(lines: list[str]) -> tuple[list[str], list[str]]:
    """``lines`` with each top-level block that is not valid reST turned into a literal block (as written).

    Returns (the new lines, the problems found); when that is not enough, all but the first paragraph is literal.
    """
    problems = rest_problems(lines)
    found = [text if line is None else f"line {line}: {text}" for line, text in problems]
    if not problems:
        return lines, found
    chunks, bad = _chunks(lines), set()
    for line, text in problems:
        if line is None:       # a substitution: the blocks that hold it
            ref = text.rpartition(": ")[2]
            bad |= {c for c in chunks if any(ref in row for row in lines[c[0]:c[1]])}
        else:
            bad |= {c for c in chunks if c[0] < line <= c[1]} or set([c for c in chunks if c[0] < line][-1:])
    fixed: list[str] = []
    at = 0
    for chunk in sorted(bad):
        fixed += lines[at:chunk[0]] + _literal(lines[chunk[0]:chunk[1]])
        at = chunk[1]
    fixed += lines[at:]
    if bad and not rest_problems(fixed):
        return fixed, found
    blank = next((i for i, row in enumerate(lines) if not row.strip()), len(lines))
    head = lines[:blank] if not rest_problems(lines[:blank]) else []
    return [*head, *_literal(lines[len(head):])], found


def _first_report(app: Sphinx, name: str) -> bool:
    """True the first time ``name`` is reported in this build, whichever process asks (autosummary, readers)."""
    try:
        (Path(app.doctreedir) / _REPORTS / name).touch(exist_ok=False)
        return True
    except FileExistsError:
        return False


def _reset_reports(app: Sphinx) -> None:
    folder = Path(app.doctreedir) / _REPORTS
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)


_REPORTS = "vpr-site-docstrings"


def _docstring_as_written(app: Sphinx, what: str, name: str, obj, options, lines: list[str]) -> None:
    home = obj.__name__ if what == "module" else getattr(obj, "__module__", None) or ""
    if not lines or not home.startswith("vpr_nb") or not (what == "module" or name.startswith(home + ".")):
        return            # an imported name (tqdm, a re-export) is documented where it is defined, if at all
    fixed, problems = as_valid_rest(list(lines))
    if problems:
        lines[:] = fixed
        if _first_report(app, name):
            LOGGER.warning(f"reference: the docstring of {name} is not valid reST ({problems[0]}); fix it (the part "
                           "that is not is shown as written)")


# --- the commands' --help, run at build time --------------------------------------------------------------------------

class CommandHelp(SphinxDirective):
    """``.. command-help:: vpr_nb.train``: a literal block of ``python -m vpr_nb.train --help``."""

    required_arguments = 1
    option_spec = {"script": directives.unchanged}

    def run(self) -> list[nodes.Node]:
        module = self.arguments[0]
        env = {**os.environ, "COLUMNS": HELP_COLUMNS, "PYTHONWARNINGS": "ignore"}
        env.pop("VPR_NB_RESULTS_DIR", None)
        try:
            proc = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True,
                                  env=env, timeout=HELP_TIMEOUT_S, cwd=self.config.vpr_site_root)
        except subprocess.TimeoutExpired:
            return [self.state.document.reporter.warning(f"python -m {module} --help took over {HELP_TIMEOUT_S} s",
                                                          line=self.lineno)]
        if proc.returncode != 0 or not proc.stdout.strip():
            return [self.state.document.reporter.warning(
                f"python -m {module} --help exited with {proc.returncode}: {proc.stderr.strip()[-500:]}",
                line=self.lineno)]
        text = proc.stdout.rstrip()
        block = nodes.literal_block(text, text, language="text", classes=["command-help"])
        return [block]


# --- build-finished: MathJax's files, index.html ----------------------------------------------------------------------

def mathjax_dir() -> Path:
    spec = find_spec(MATHJAX_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"the site needs the Python package {MATHJAX_PACKAGE} (MathJax's files): "
                           "make dev installs it (requirements-dev.txt)")
    return Path(next(iter(spec.submodule_search_locations))) / "static" / "mathjax"


def _copy_mathjax(app: Sphinx) -> None:
    source, dest = mathjax_dir(), Path(app.outdir) / "_static" / PurePosixPath(MATHJAX_SCRIPT).parent
    for part in MATHJAX_PARTS:
        src = source / part
        if src.is_dir():
            shutil.copytree(src, dest / part, dirs_exist_ok=True)
        else:
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / part)


REDIRECT = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>vpr-notebooks</title>
<meta http-equiv="refresh" content="0; url={root}.html"><link rel="canonical" href="{root}.html"></head>
<body><p>The course's home page is <a href="{root}.html">{root}.html</a>.</p></body></html>
"""


def _finish(app: Sphinx, exc: Exception | None) -> None:
    if exc is not None or app.builder.format != "html":
        return
    _copy_mathjax(app)
    if app.config.root_doc != "index":
        (Path(app.outdir) / "index.html").write_text(REDIRECT.format(root=app.config.root_doc), encoding="utf-8")


def _check_mathjax(app: Sphinx) -> None:
    mathjax_dir()                        # fail at the start, not after reading every page


def setup(app: Sphinx) -> dict:
    app.add_config_value("vpr_site_root", "", "env")
    app.add_config_value("vpr_site_repository", "", "env")
    app.add_config_value("vpr_site_branch", "main", "env")
    app.add_post_transform(RepositoryFileLinks)
    app.add_post_transform(NotebookNameLinks)
    app.add_transform(WidgetNotes)
    app.add_directive("command-help", CommandHelp)
    app.connect("autodoc-process-docstring", _docstring_as_written, priority=900)   # after napoleon's (500)
    app.connect("builder-inited", _check_mathjax, priority=100)
    app.connect("builder-inited", _reset_reports, priority=100)     # before autosummary's stubs (priority 500)
    app.connect("build-finished", _finish)
    app.add_css_file("vpr_site.css")
    return {"parallel_read_safe": True, "parallel_write_safe": True, "version": "1"}
