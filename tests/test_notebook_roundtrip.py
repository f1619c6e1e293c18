"""Opening and saving a notebook in JupyterLab changes neither the .ipynb nor its paired .py.

JupyterLab reads and writes notebooks through the server's contents manager, which jupytext replaces
with its pairing one (jupytext's server extension jupyterlab_jupytext, enabled when jupytext is installed). When a kernel connects, the
front end writes the kernel's spec into ``metadata.kernelspec`` (name, display name, language) and the
kernel's ``language_info`` into ``metadata.language_info``; autosave then writes the notebook back.
This test does the same without a browser: it reads every course notebook of a temporary copy with
that contents manager, puts in what a connected ipykernel reports, saves it, and compares the bytes of
both files with the originals. (``language_info.version`` is the Python that executed the notebook:
under another Python, that one value is rewritten; the test checks that nothing else is.)
"""
import asyncio
import json
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))


def _kernel_metadata():
    """What JupyterLab writes on connecting to the course's kernel: its spec and its language_info."""
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import start_new_kernel

    spec = KernelSpecManager().get_kernel_spec("python3")
    km, kc = start_new_kernel(kernel_name="python3")
    try:
        reply = kc.kernel_info(reply=True, timeout=60)
    finally:
        kc.stop_channels()
        km.shutdown_kernel(now=True)
    return ({"name": "python3", "display_name": spec.display_name, "language": spec.language},
            reply["content"]["language_info"])


async def _open_and_save(folder: Path, names, kernelspec, language_info):
    from jupyter_server.services.contents.largefilemanager import AsyncLargeFileManager
    from jupytext.async_contentsmanager import build_async_jupytext_contents_manager_class

    cm = build_async_jupytext_contents_manager_class(AsyncLargeFileManager)(root_dir=str(folder))
    for name in names:
        model = await cm.get(name, content=True, type="notebook")
        model["content"]["metadata"]["kernelspec"] = dict(kernelspec)
        model["content"]["metadata"]["language_info"] = dict(language_info)
        await cm.save(model, name)


@pytest.mark.slow
def test_opening_and_saving_a_notebook_changes_neither_file(tmp_path):
    shutil.copy(ROOT / "notebooks" / "jupytext.toml", tmp_path)
    for nb in NOTEBOOKS:
        shutil.copy2(nb, tmp_path)
        shutil.copy2(nb.with_suffix(".py"), tmp_path)
    kernelspec, language_info = _kernel_metadata()
    asyncio.run(_open_and_save(tmp_path, [nb.name for nb in NOTEBOOKS], kernelspec, language_info))

    for nb in NOTEBOOKS:
        stored = json.loads(nb.read_text(encoding="utf-8"))
        assert stored["metadata"]["kernelspec"] == kernelspec, (
            f"{nb.name}: stored kernelspec {stored['metadata']['kernelspec']} is not what the kernel reports "
            f"({kernelspec}), so JupyterLab rewrites it on opening")
        assert (tmp_path / nb.with_suffix(".py").name).read_bytes() == nb.with_suffix(".py").read_bytes(), \
            f"saving {nb.name} rewrote its paired script"
        saved = (tmp_path / nb.name).read_bytes()
        if stored["metadata"]["language_info"].get("version") == language_info.get("version"):
            assert saved == nb.read_bytes(), f"opening and saving {nb.name} changed it"
        else:                      # executed under another Python than this one: only that value may change
            expected = json.loads(nb.read_text(encoding="utf-8"))
            expected["metadata"]["language_info"]["version"] = language_info["version"]
            assert json.loads(saved) == expected, f"opening {nb.name} changed more than language_info.version"
