"""The course as a website (docs/site/, ``make site``): built from the stored notebooks, strict, and whole.

The site is built once per run into a temporary folder, with ``docs/site/build.py`` (Sphinx, warnings as errors,
``--keep-going``; no notebook executed), and checked here:

* it builds with no warning, and a tiny copy with one broken link and one missing figure does not (both are
  reported); a tiny copy whose pyproject.toml sets ``[project.urls] Repository`` gets Binder and Colab
  buttons, and the real site gets them only when the real pyproject.toml sets it;
* one page per notebook 00-08, in course order, holding every figure the notebook stores; a note on every
  widget cell; README as the home page, every docs/ page, a package reference with a page for every public
  module of vpr_nb, every command's ``--help``;
* every internal link, image, script and stylesheet of every page reaches a file of the site (and a link's
  ``#anchor`` an id of its page);
* in a browser (headless Debian Chromium through Playwright, the site served on 127.0.0.1, every request
  off the machine refused): the home page and notebook 03 load, MathJax typesets every equation (no raw TeX
  left), every figure loads, every same-site link reaches a file. A screenshot of notebook 03's widget cell
  is left as ``tmp_path / "site_notebook_03.png"``.

The browser test needs ``playwright`` and ``/usr/bin/chromium``; without them it fails with instructions,
unless ``VPR_NB_ALLOW_SKIP_BROWSER=1`` is set (``make test`` sets it when chromium is missing), as
tests/test_browser.py does.
"""
from __future__ import annotations

import base64
import functools
import html.parser
import http.server
import importlib.util
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

REPO = Path(__file__).resolve().parents[1]
SITE = REPO / "docs" / "site"
NOTEBOOKS = sorted((REPO / "notebooks").glob("[0-9][0-9]_*.ipynb"))
DOCS = sorted((REPO / "docs").glob("*.md"))
BUILD_TIMEOUT_S = 600           # `make site` must take at most 3 min on 2 cores; this only stops a hung build
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
SKIP_ENV = "VPR_NB_ALLOW_SKIP_BROWSER"
UI_TIMEOUT_MS = 30_000
BROWSER_NOTEBOOK = "03_distance_ranking_weighted_loss"     # equations, figures and a widget cell


def _module(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


site_build = _module("site_build", SITE / "build.py")


def _require_sphinx() -> None:
    missing = [m for m in ("sphinx", "myst_nb", "sphinx_book_theme") if importlib.util.find_spec(m) is None]
    if missing or importlib.util.find_spec("sphinx-mathjax-offline") is None:
        pytest.fail(f"the site needs {', '.join(missing) or 'sphinx-mathjax-offline'}: `make dev` installs them "
                    "(requirements-dev.txt)", pytrace=False)


def _build(root: Path, out: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    _require_sphinx()
    return subprocess.run([sys.executable, str(SITE / "build.py"), "--root", str(root), "--out", str(out), "-q",
                           *args], capture_output=True, text=True, timeout=BUILD_TIMEOUT_S,
                          env={**os.environ, **(env or {})})


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The whole site, built once: (html folder, the build's output, seconds)."""
    out = tmp_path_factory.mktemp("site")
    start = time.monotonic()
    proc = _build(REPO, out)
    took = time.monotonic() - start
    output = proc.stdout + proc.stderr
    if proc.returncode != 0:
        pytest.fail(f"the site's build failed (exit {proc.returncode}); its warnings:\n{output[-6000:]}", pytrace=False)
    return out / "html", output, took


def _page(html_dir: Path, docname: str) -> str:
    path = html_dir / f"{docname}.html"
    assert path.is_file(), f"no page {docname}.html in the site"
    return path.read_text(encoding="utf-8")


def _stored_pngs(notebook: Path) -> int:
    cells = json.loads(notebook.read_text(encoding="utf-8"))["cells"]
    return sum("image/png" in out.get("data", {}) for c in cells if c["cell_type"] == "code" for out in c["outputs"])


# --- the build ------------------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_the_site_builds_with_no_warning(built, record_property):
    html_dir, output, took = built
    record_property("build_seconds", round(took, 1))
    assert "site: " in output and "no notebook executed" in output, output[-2000:]
    assert (html_dir / "index.html").is_file() and (html_dir / "README.html").is_file()
    assert 'url=README.html' in (html_dir / "index.html").read_text(), "index.html must lead to the home page"


@pytest.mark.slow
def test_a_page_per_notebook_in_course_order_with_every_stored_figure(built):
    html_dir, _, _ = built
    assert len(NOTEBOOKS) >= 9
    for nb in NOTEBOOKS:
        page = _page(html_dir, f"notebooks/{nb.stem}")
        images = re.findall(r'<img [^>]*src="(\.\./_images/[^"]+)"', page)     # outputs' figures (no Markdown image)
        stored = _stored_pngs(nb)
        assert len(images) == stored, f"{nb.name}: {stored} stored figures, {len(images)} on its page"
        for src in images:
            assert (html_dir / "notebooks" / unquote(src)).resolve().is_file(), f"{nb.name}: {src} is missing"
        assert f"<title>{nb.name[:2]} · " in page, f"{nb.name}: the page's title is not its first heading"
        markdown = "\n".join("".join(c["source"]) for c in json.loads(nb.read_text(encoding="utf-8"))["cells"]
                             if c["cell_type"] == "markdown")
        tables = len(re.findall(r"^\|?\s*:?-{3,}:?\s*\|", markdown, flags=re.M))     # a Markdown table's rule
        shown = page.count("<table")
        assert shown == tables, f"{nb.name}: {tables} Markdown tables, {shown} on its page"
    home = _page(html_dir, "README")
    nav = re.findall(r'href="(notebooks/\d\d_\w+)\.html"', home.split('class="bd-sidebar-primary', 1)[1])
    order = list(dict.fromkeys(nav))
    assert order == [f"notebooks/{nb.stem}" for nb in NOTEBOOKS], f"the navigation lists the notebooks as {order}"


@pytest.mark.slow
def test_every_widget_cell_has_a_note_over_its_static_output(built):
    html_dir, _, _ = built
    vpr_site = _module("vpr_site_for_test", SITE / "vpr_site.py")
    total = 0
    for nb in NOTEBOOKS:
        cells = json.loads(nb.read_text(encoding="utf-8"))["cells"]
        widgets = sum(bool(vpr_site.WIDGET_CELL.search("".join(c["source"])))
                      for c in cells if c["cell_type"] == "code")
        notes = _page(html_dir, f"notebooks/{nb.stem}").count("widget-note")
        assert notes == widgets, f"{nb.name}: {widgets} widget cells, {notes} notes"
        total += widgets
    assert total >= 2, "notebooks 03 and 06 hold widget cells; none was found"


@pytest.mark.slow
def test_home_docs_reference_and_commands(built):
    html_dir, _, _ = built
    home = _page(html_dir, "README")
    assert "Start here" in home and "The notebooks" in home
    for nb in NOTEBOOKS:     # README's table of the notebooks links each page
        assert f'href="notebooks/{nb.stem}.html"' in home, f"the home page does not link {nb.name}"
    for doc in DOCS:
        assert f'href="docs/{doc.stem}.html"' in home, f"the home page's navigation misses docs/{doc.name}"
        _page(html_dir, f"docs/{doc.stem}")
    _page(html_dir, "site/about")
    reference = _page(html_dir, "site/reference")
    modules = site_build.public_modules(REPO)
    assert "vpr_nb.train" in modules and "vpr_nb.losses" in modules and not any("._" in m for m in modules)
    for module in modules:
        assert f'href="api/{module}.html"' in reference, f"the reference does not list {module}"
        assert module in _page(html_dir, f"site/api/{module}")
    from vpr_nb.__main__ import COMMANDS
    commands = _page(html_dir, "site/commands")
    blocks = re.findall(r'<div class="command-help highlight-text notranslate">.*?</pre>', commands, re.S)
    assert len(blocks) == len(COMMANDS), f"{len(COMMANDS)} commands, {len(blocks)} --help outputs on the page"
    for script, module, _ in COMMANDS:
        assert f"python -m {module}" in commands and (script is None or f"<h2>{script}" in commands)
        assert any("usage:" in b and module.split(".")[-1] in b for b in blocks), f"no --help of {module}"


class _Refs(html.parser.HTMLParser):
    """The href/src of a page's links, images, scripts and stylesheets, and its ids."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if attrs.get("id"):
            self.ids.add(attrs["id"])
        ref = attrs.get("href") if tag in ("a", "link") else attrs.get("src") if tag in ("img", "script") else None
        if ref:
            self.refs.append(ref)


def _parse(path: Path) -> _Refs:
    refs = _Refs()
    refs.feed(path.read_text(encoding="utf-8"))
    return refs


def _site_file(html_dir: Path, page: Path, ref: str) -> tuple[Path, str] | None:
    """The file (and anchor) a relative reference of ``page`` points to; None for another site or a data: URL."""
    parts = urlsplit(ref)
    if parts.scheme or parts.netloc or ref.startswith(("mailto:", "javascript:")):
        return None
    target = (page.parent / unquote(parts.path)).resolve() if parts.path else page
    if target.is_dir():
        target = target / "index.html"
    return target, parts.fragment


@pytest.mark.slow
def test_every_internal_link_and_image_reaches_a_file(built):
    html_dir, _, _ = built
    pages = [p for p in html_dir.rglob("*.html") if not p.relative_to(html_dir).parts[0].startswith("_")]
    parsed = {p.resolve(): _parse(p) for p in pages}
    broken = []
    for page, refs in parsed.items():
        for ref in refs.refs:
            found = _site_file(html_dir, page, ref)
            if found is None:
                continue
            target, anchor = found
            if not target.is_file() or html_dir.resolve() not in target.parents:
                broken.append(f"{page.relative_to(html_dir.resolve())}: {ref} (no such file)")
            elif anchor and target.suffix == ".html" and target in parsed and anchor not in parsed[target].ids:
                broken.append(f"{page.relative_to(html_dir.resolve())}: {ref} (no id #{anchor})")
    assert len(pages) > 100
    assert not broken, f"{len(broken)} broken references:\n" + "\n".join(broken[:40])


# --- launch buttons: from pyproject.toml's [project.urls] Repository, nowhere else ------------------------------------

@pytest.mark.slow
def test_launch_buttons_only_when_the_repository_address_is_set(built):
    import tomllib
    html_dir, output, _ = built
    urls = tomllib.loads((REPO / "pyproject.toml").read_text())["project"].get("urls", {})
    page = _page(html_dir, f"notebooks/{NOTEBOOKS[0].stem}")
    if "Repository" in urls:
        assert "mybinder.org/v2/" in page and "launch buttons: Binder and Colab on the notebook pages" in output
    else:
        assert "mybinder.org" not in page and "colab.research.google.com" not in page
        assert "launch buttons: none, pyproject.toml has no [project.urls] Repository" in output


_PNG = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8DwHwAFBQIAX8jx0gAAAABJ"
                        "RU5ErkJggg==")       # a 1x1 PNG


def _tiny_repo(root: Path, *, repository: str | None = None, broken: bool = False) -> Path:
    """A tiny copy of the repository's shape: pyproject.toml, README.md, one docs page, one notebook with a figure."""
    (root / "docs").mkdir(parents=True)
    (root / "notebooks").mkdir()
    urls = f'\n[project.urls]\nRepository = "{repository}"\n' if repository else ""
    (root / "pyproject.toml").write_text(f'[project]\nname = "tiny"\nversion = "0.0.1"\n{urls}')
    (root / "LICENSE").write_text("MIT\n")
    link = "docs/missing.md" if broken else "docs/guide.md"
    (root / "README.md").write_text(f"# Tiny course\n\nRead [the guide]({link}), "
                                    "[the notebook](notebooks/00_tiny.ipynb) and the [licence](LICENSE).\n")
    figure = "missing.png" if broken else "figure.png"
    (root / "docs" / "figure.png").write_bytes(_PNG)
    (root / "docs" / "guide.md").write_text(f"# Guide\n\nThe loss is $$w = 1 + d$$\n\n![a figure]({figure})\n\n"
                                            "Back [home](../README.md).\n")
    notebook = {"nbformat": 4, "nbformat_minor": 5,
                "metadata": {"kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"},
                             "language_info": {"name": "python"}},
                "cells": [{"cell_type": "markdown", "id": "a", "metadata": {},
                           "source": "# 00 · Tiny\n\nAn equation: $\\sigma = 800$ m."},
                          {"cell_type": "code", "id": "b", "metadata": {}, "execution_count": 1,
                           "source": "plot()", "outputs": [{"output_type": "display_data", "metadata": {},
                                                           "data": {"image/png": base64.b64encode(_PNG).decode(),
                                                                    "text/plain": "<Figure>"}}]}]}
    (root / "notebooks" / "00_tiny.ipynb").write_text(json.dumps(notebook))
    return root


@pytest.mark.slow
def test_launch_buttons_come_from_pyproject(tmp_path):
    root = _tiny_repo(tmp_path / "repo", repository="https://github.com/someone/some-course")
    proc = _build(root, tmp_path / "out", "--course-only", env={"VPR_SITE_BRANCH": "spring"})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    page = (tmp_path / "out" / "html" / "notebooks" / "00_tiny.html").read_text(encoding="utf-8")
    assert ("https://mybinder.org/v2/gh/someone/some-course/spring?urlpath=lab/tree/notebooks/00_tiny.ipynb"
            in page), "no Binder button opening the notebook in JupyterLab"
    assert "https://colab.research.google.com/github/someone/some-course/blob/spring/notebooks/00_tiny.ipynb" in page
    home = (tmp_path / "out" / "html" / "README.html").read_text(encoding="utf-8")
    assert "https://github.com/someone/some-course/blob/spring/LICENSE" in home, "a repository file: a link there"
    assert "mybinder.org" not in home, "launch buttons belong on notebook pages only"


@pytest.mark.slow
def test_the_build_fails_on_a_broken_link_a_missing_figure_or_a_broken_notebook(tmp_path):
    good = _build(_tiny_repo(tmp_path / "good"), tmp_path / "good-out", "--course-only")
    assert good.returncode == 0, "the tiny copy must build when nothing is broken:\n" + good.stdout + good.stderr
    assert "mybinder.org" not in (tmp_path / "good-out" / "html" / "notebooks" / "00_tiny.html").read_text()
    bad = _build(_tiny_repo(tmp_path / "bad", broken=True), tmp_path / "bad-out", "--course-only")
    output = bad.stdout + bad.stderr
    assert bad.returncode != 0, f"a broken link and a missing figure must fail the build:\n{output}"
    assert "docs/missing" in output and "missing.png" in output, f"both faults must be reported:\n{output}"
    assert "the build failed" in output
    unreadable = _tiny_repo(tmp_path / "notebook")
    (unreadable / "notebooks" / "01_broken.ipynb").write_text('{"cells": [')       # a notebook cut short
    failed = _build(unreadable, tmp_path / "notebook-out", "--course-only")
    assert failed.returncode != 0 and "Notebook does not appear to be JSON" in failed.stdout + failed.stderr, \
        "a notebook that cannot be read must fail the build"


# --- in a browser ---------------------------------------------------------------------------------------------------

def _require_browser() -> None:
    missing = []
    if importlib.util.find_spec("playwright") is None:
        missing.append("the Python package playwright")
    if not (CHROMIUM.is_file() and os.access(CHROMIUM, os.X_OK)):
        missing.append(f"Debian's chromium at {CHROMIUM}")
    if not missing:
        return
    message = "the site's browser test needs " + " and ".join(missing) + ". "
    if os.environ.get(SKIP_ENV) == "1":
        pytest.skip(message + f"Skipped because {SKIP_ENV}=1.")
    pytest.fail(message + "Install them with `make dev` (playwright) and `apt-get install -y chromium` (do NOT "
                f"run `playwright install`), or set {SKIP_ENV}=1 to skip this test.", pytrace=False)


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


@pytest.fixture
def served(built):
    """The built site on http://127.0.0.1:<free port>/, stopped afterwards."""
    _require_browser()
    html_dir, _, _ = built
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(html_dir)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", html_dir
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


_TEXT_OUTSIDE_CODE_AND_MATHS = """() => {
    const main = document.querySelector('main') || document.body;
    const copy = main.cloneNode(true);
    copy.querySelectorAll('pre, code, mjx-container, script, style, .highlight').forEach(e => e.remove());
    return copy.textContent;
}"""


def _check_page(page, base: str, html_dir: Path) -> dict:
    """Figures loaded and every same-site link reaches a file of the site; returns counts."""
    page.wait_for_function("Array.from(document.images).every(i => i.complete)", timeout=UI_TIMEOUT_MS)
    images = page.evaluate("Array.from(document.images).map(i => [i.currentSrc || i.src, i.naturalWidth])")
    unloaded = [src for src, width in images if width == 0]
    assert not unloaded, f"{page.url}: figures that did not load: {unloaded}"
    hrefs = page.evaluate("Array.from(document.querySelectorAll('a[href]')).map(a => a.href)")
    broken = []
    for href in hrefs:
        parts = urlsplit(href)
        if f"{parts.scheme}://{parts.netloc}" != base:
            continue
        path = html_dir / unquote(parts.path).lstrip("/")
        if not (path.is_file() or (path / "index.html").is_file()):
            broken.append(href)
    assert not broken, f"{page.url}: same-site links to no file: {broken}"
    return {"images": len(images), "links": len(hrefs)}


def _wait_for_mathjax(page) -> None:
    page.wait_for_function("window.MathJax && MathJax.startup && MathJax.startup.promise", timeout=UI_TIMEOUT_MS)
    page.evaluate("MathJax.startup.promise")


@pytest.mark.slow
@pytest.mark.browser
def test_the_site_in_a_browser(served, tmp_path):
    from playwright.sync_api import sync_playwright

    base, html_dir = served
    refused, failed = [], []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS,
                                     timeout=UI_TIMEOUT_MS)
        try:
            page = browser.new_page(viewport={"width": 1300, "height": 900})
            page.set_default_timeout(UI_TIMEOUT_MS)
            page.route("**/*", lambda route: route.continue_() if route.request.url.startswith(base + "/")
                       else (refused.append(route.request.url), route.abort()))
            page.on("response", lambda r: failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)

            page.goto(base + "/", wait_until="load")
            page.wait_for_url(f"{base}/README.html", timeout=UI_TIMEOUT_MS)      # index.html leads home
            assert "vpr-notebooks" in page.title()
            assert page.locator("nav a", has_text="03 · DW-T-Loss").count() >= 1, "the navigation lists the notebooks"
            home = _check_page(page, base, html_dir)

            page.goto(f"{base}/notebooks/{BROWSER_NOTEBOOK}.html", wait_until="load")
            _wait_for_mathjax(page)
            maths = page.locator("main .math").count()
            typeset = page.locator("main .math mjx-container").count()
            assert maths >= 20, f"notebook {BROWSER_NOTEBOOK[:2]} should hold many equations, found {maths}"
            assert typeset == maths, f"MathJax typeset {typeset} of the page's {maths} equations"
            assert page.locator("mjx-merror, [data-mjx-error]").count() == 0, "MathJax reported a TeX error"
            text = page.evaluate(_TEXT_OUTSIDE_CODE_AND_MATHS)
            raw = [m for m in ("$$", "\\(", "\\[", "\\frac", "\\sigma", "\\mathrm") if m in text]
            assert not raw, f"raw TeX left on the page outside code: {raw}"
            counts = _check_page(page, base, html_dir)
            assert counts["images"] == _stored_pngs(REPO / "notebooks" / f"{BROWSER_NOTEBOOK}.ipynb")
            note = page.locator(".widget-note").first
            note.scroll_into_view_if_needed()
            assert "no kernel" in note.inner_text()
            page.screenshot(path=str(tmp_path / "site_notebook_03.png"))
        finally:
            browser.close()
    assert not refused, f"the site asked for files off the machine (it must work offline): {refused}"
    assert not failed, f"requests the local server could not answer: {failed}"
    assert home["links"] > 10 and (tmp_path / "site_notebook_03.png").stat().st_size > 0
