"""Build the course's website: ``make site``, or ``python docs/site/build.py [--out DIR] [--root ROOT]``.

1. Stages the sources into ``OUT/source``, with the repository's own paths: README.md (the home page, with the
   site's navigation appended to the copy), docs/*.md, notebooks/NN_*.ipynb as stored, and docs/site/*.md (the
   package reference, the commands, about the site). Nothing is written into the repository.
2. Runs Sphinx (``docs/site/conf.py``) with warnings as errors and ``--keep-going`` (every warning is listed, then the
   build fails): a broken link, a missing image or a notebook that does not render fails it. No notebook is
   executed.
3. Prints where to open the site: ``OUT/html/index.html``.

``--root`` builds another copy of the repository (the tests build tiny ones); ``--course-only`` builds README, docs/
and the notebooks alone, without this folder's pages (the package reference and the commands' ``--help`` import
vpr_nb and torch; the about page links to both).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

SITE_DIR = Path(__file__).resolve().parent
REPO = SITE_DIR.parent.parent
# docs/ pages in the order README's "More material" gives them; any other docs/*.md page follows, by name
DOCS_ORDER = ("teaching", "reproduction", "performance", "development", "architecture")
SITE_PAGES = ("reference", "commands", "about")      # this folder's pages, in the navigation's order
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".gif", ".svg", ".webp"}
SPECIAL_PAGES = {"index.html", "genindex.html", "search.html", "py-modindex.html"}


def launch_buttons_line(root: Path) -> str:
    """One line on the launch buttons: whether pyproject.toml's [project.urls] Repository gives them an address."""
    sys.path.insert(0, str(SITE_DIR))
    from vpr_site import repository_url
    repository = repository_url(tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8")))
    if repository:
        return (f"site: launch buttons: Binder and Colab on the notebook pages, from [project.urls] Repository = "
                f"{repository} (branch {os.environ.get('VPR_SITE_BRANCH') or 'main'})")
    return ("site: launch buttons: none, pyproject.toml has no [project.urls] Repository (set it there, once, to get "
            "Binder and Colab buttons on the notebook pages)")


def _pages(root: Path, with_reference: bool) -> tuple[list[str], list[str], list[str]]:
    """(notebooks, docs pages, site pages) as docnames, in the order the site's navigation lists them."""
    notebooks = [f"notebooks/{p.stem}" for p in sorted((root / "notebooks").glob("[0-9][0-9]_*.ipynb"))]
    docs = sorted((p.stem for p in (root / "docs").glob("*.md")),
                  key=lambda s: (DOCS_ORDER.index(s) if s in DOCS_ORDER else len(DOCS_ORDER), s))
    site = sorted((p.stem for p in SITE_DIR.glob("*.md") if with_reference),
                  key=lambda s: (SITE_PAGES.index(s) if s in SITE_PAGES else len(SITE_PAGES), s))
    return notebooks, [f"docs/{d}" for d in docs], [f"site/{s}" for s in site]


def public_modules(root: Path) -> list[str]:
    """Every public module of ``root/vpr_nb``, from the files: no part of its name starts with ``_``."""
    package = root / "vpr_nb"
    found = []
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(root).with_suffix("")
        parts = list(rel.parts[:-1]) if rel.name == "__init__" else list(rel.parts)
        if "__pycache__" in parts or any(part.startswith("_") for part in parts[1:]):
            continue
        if all((root / Path(*parts[:i]) / "__init__.py").is_file() for i in range(1, len(parts))):
            found.append(".".join(parts))
    return sorted(set(found))


def layer_groups(root: Path, modules: list[str]) -> list[tuple[str, list[str]]]:
    """(heading, modules) by the package's layers (pyproject's import-linter "layers" contract), top layer first.

    The package itself comes first; a module the contract does not place (none today) is listed last.
    """
    contracts = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8")).get("tool", {}) \
        .get("importlinter", {}).get("contracts", [])
    contract = next((c for c in contracts if c.get("type") == "layers"), {})
    layers = [[n.strip() for n in layer.split(":")] for layer in contract.get("layers", [])]   # top first
    named = contract.get("name", "").partition(":")[2].split("->")                              # bottom first
    names = [n.strip() for n in reversed(named)] if len(named) == len(layers) else [""] * len(layers)
    groups = [("The package", [m for m in modules if m == "vpr_nb"])]
    for i, (members, name) in enumerate(zip(layers, names)):
        number = len(layers) - i
        inside = [m for m in modules if m != "vpr_nb" and m.split(".")[1] in members]
        groups.append((f"Layer {number}: {name}" if name else f"Layer {number}", inside))
    placed = {m for _, group in groups for m in group}
    groups.append(("Not in a layer", [m for m in modules if m not in placed]))
    return [(heading, group) for heading, group in groups if group]


def _reference_listing(root: Path) -> str:
    """The reference page's module lists: one autosummary table (and generated page) per module."""
    blocks = []
    for heading, group in layer_groups(root, public_modules(root)):
        blocks += [f"## {heading}", "", "```{eval-rst}", ".. autosummary::", "   :toctree: api", "",
                   *(f"   {m}" for m in group), "```", ""]
    return "\n".join(blocks)


def _toctree(caption: str, entries: list[str]) -> str:
    return "\n".join(["", "```{toctree}", ":hidden:", f":caption: {caption}", "", *entries, "```", ""])


def stage(root: Path, source: Path, with_reference: bool) -> list[str]:
    """Copy the site's sources from ``root`` into ``source``; returns the docnames staged."""
    if source.exists():
        shutil.rmtree(source)
    notebooks, docs, site = _pages(root, with_reference)
    for doc in docs:
        _copy(root / f"{doc}.md", source / f"{doc}.md")
    for nb in notebooks:
        _copy(root / f"{nb}.ipynb", source / f"{nb}.ipynb")
    _copy_assets(root, source)
    for page in site:
        _copy(SITE_DIR / f"{page.removeprefix('site/')}.md", source / f"{page}.md")
    if with_reference:
        reference = source / "site" / "reference.md"
        reference.write_text(reference.read_text(encoding="utf-8") + "\n" + _reference_listing(root), encoding="utf-8")
    readme = (root / "README.md").read_text(encoding="utf-8")
    navigation = (_toctree("The notebooks", notebooks) + _toctree("For teachers and developers", docs)
                  + (_toctree("Reference and this site", site) if site else ""))
    (source / "README.md").write_text(readme.rstrip("\n") + "\n" + navigation, encoding="utf-8")
    return ["README", *notebooks, *docs, *site]


def _copy_assets(root: Path, source: Path) -> None:
    """What the pages show besides themselves: every file under docs/ (but the site's own sources, docs/site/), and
    images under notebooks/ and the root."""
    site_sources = root / SITE_DIR.relative_to(REPO)
    for path in (root / "docs").rglob("*"):
        if path.is_file() and path.suffix != ".md" and site_sources not in path.parents:
            _copy(path, source / path.relative_to(root))
    for path in [*(root / "notebooks").rglob("*"), *root.glob("*")]:
        if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES and ".ipynb_checkpoints" not in path.parts:
            _copy(path, source / path.relative_to(root))


def _copy(src: Path, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src, dest)


def build(root: Path, out: Path, *, with_reference: bool = True, jobs: str = "auto", quiet: bool = False) -> int:
    """Stage and build; returns Sphinx's exit status (0: built with no warning)."""
    root, out = root.resolve(), out.resolve()
    start = time.monotonic()
    print(launch_buttons_line(root))
    docnames = stage(root, out / "source", with_reference)
    for stale in (out / "html", out / "doctrees", out / "jupyter_execute"):
        if stale.exists():
            shutil.rmtree(stale)
    env = {**os.environ, "VPR_SITE_ROOT": str(root), "VPR_SITE_REFERENCE": "1" if with_reference else "0",
           # the package reference documents the vpr_nb of the tree being built
           "PYTHONPATH": os.pathsep.join([str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
    cmd = [sys.executable, "-m", "sphinx", "-b", "html", "-W", "--keep-going", "-E", "-j", jobs,
           "-c", str(SITE_DIR), "-d", str(out / "doctrees"), str(out / "source"), str(out / "html")]
    if quiet:
        cmd.append("-q")
    status = subprocess.run(cmd, env=env).returncode
    took = time.monotonic() - start
    if status == 0:
        rel = [p.relative_to(out / "html") for p in (out / "html").rglob("*.html")]
        pages = [p for p in rel if p.as_posix() not in SPECIAL_PAGES and not p.parts[0].startswith("_")]
        modules = sum(p.parent.name == "api" for p in pages)
        print(f"site: {len(pages)} pages ({sum(d.startswith('notebooks/') for d in docnames)} notebooks, "
              f"{sum(d.startswith('docs/') for d in docnames)} docs pages, {modules} module pages) built in "
              f"{took:.0f} s, no notebook executed. Open {out / 'html' / 'index.html'}")
        print(f"  or serve it: {Path(sys.executable).name} -m http.server --bind 127.0.0.1 --directory "
              f"{out / 'html'} 8000, then http://127.0.0.1:8000/")
    else:
        print(f"site: the build failed after {took:.0f} s (warnings are errors; each is listed above)",
              file=sys.stderr)
    return status


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python docs/site/build.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=REPO, help="the repository to build (default: this one)")
    parser.add_argument("--out", type=Path, default=REPO / "_site", help="build folder (default: _site)")
    parser.add_argument("--course-only", action="store_true",
                        help="README, docs/ and the notebooks only: no package reference, commands or about page")
    parser.add_argument("-j", "--jobs", default="auto", help="Sphinx's parallel jobs (default: auto)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and the closing lines")
    args = parser.parse_args(argv)
    return build(args.root, args.out, with_reference=not args.course_only, jobs=args.jobs, quiet=args.quiet)


if __name__ == "__main__":
    sys.exit(main())
