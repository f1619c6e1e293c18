"""Stored notebooks carry no metadata that differs between Pythons, and Jupyter's save keeps it that way."""
import json
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest

from vpr_nb import authoring

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_stored_notebooks_carry_no_python_version(path):
    meta = json.loads(path.read_text(encoding="utf-8"))["metadata"]
    assert "version" not in meta.get("language_info", {}), (
        f"{path.name} stores the Python version it last ran on; re-execute it with `make notebook NB=...` "
        f"(vpr_nb.authoring strips it) or drop metadata.language_info.version")


def _saved_by_jupyter(tmp_path, hook):
    from jupyter_server.services.contents.filemanager import FileContentsManager

    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("1 + 1")])
    nb.metadata["language_info"] = {"name": "python", "version": "3.13.1", "pygments_lexer": "ipython3"}
    manager = FileContentsManager(root_dir=str(tmp_path), **({"pre_save_hook": hook} if hook else {}))
    manager.save({"type": "notebook", "format": "json", "content": json.loads(nbformat.writes(nb))}, "a.ipynb")
    return json.loads((tmp_path / "a.ipynb").read_text(encoding="utf-8"))["metadata"]["language_info"]


def test_jupyter_saves_without_the_python_version_through_the_hook(tmp_path):
    assert _saved_by_jupyter(tmp_path, authoring.SAVE_HOOK) == {"name": "python", "pygments_lexer": "ipython3"}
    # without the hook Jupyter writes the kernel's version: the hook is what keeps git status clean
    assert _saved_by_jupyter(tmp_path, None)["version"] == "3.13.1"
    authoring.pre_save_hook({"type": "file", "content": "text"})          # other files: left alone


def test_the_hook_is_installed_where_the_environment_s_server_reads_it(tmp_path):
    config = tmp_path / "etc" / "jupyter" / authoring.SAVE_HOOK_CONFIG
    config.parent.mkdir(parents=True)
    config.write_text('{"ServerApp": {"port": 9999}}')                    # what else is configured stays
    assert authoring.install_save_hook(str(tmp_path)) == config
    assert json.loads(config.read_text()) == {"ServerApp": {"port": 9999},
                                              "ContentsManager": {"pre_save_hook": authoring.SAVE_HOOK}}
    code = ("from jupyter_server.serverapp import ServerApp; app = ServerApp(); app.load_config_file(); "
            "print(app.config.ContentsManager.pre_save_hook)")
    env_path = f"{tmp_path / 'etc' / 'jupyter'}"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"JUPYTER_CONFIG_PATH": env_path, "PATH": "/usr/bin:/bin"}).stdout
    assert out.strip() == authoring.SAVE_HOOK
    config.write_text("[1, 2]")
    with pytest.raises(ValueError, match="not a JSON object"):
        authoring.install_save_hook(str(tmp_path))
