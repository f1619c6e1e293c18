"""The tiny real-format datasets of data_fixtures/, for tests that copy one and break it one way."""
from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

FIX = Path(__file__).resolve().parents[1] / "data_fixtures"
_spec = importlib.util.spec_from_file_location("make_fixtures", FIX / "make_fixtures.py")
MF = importlib.util.module_from_spec(_spec)      # data_fixtures/make_fixtures.py: how each fixture is written
_spec.loader.exec_module(MF)


def copy_fixture(name: str, tmp_path: Path) -> Path:
    """A copy of ``data_fixtures/<name>`` in ``tmp_path``, to break."""
    dst = tmp_path / name
    shutil.copytree(FIX / name, dst)
    return dst


def edit_lines(path: Path, fn) -> None:
    """Rewrite a text file through ``fn`` (a list of its lines in, a list of lines out)."""
    path.write_text("\n".join(fn(path.read_text().splitlines())) + "\n")
