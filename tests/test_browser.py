"""JupyterLab in a real browser: the Eq. (4) weight explorer of notebook 03 renders and reacts.

The test starts the venv's ``jupyter lab`` on 127.0.0.1 (random free port, random token, config,
data, runtime, settings and workspace dirs under ``tmp_path``) on a temporary copy of ``notebooks/``,
so nothing in the repository is touched. Headless Debian Chromium (``/usr/bin/chromium``, driven by
Playwright for Python; no browser download) opens notebook 03, runs Run -> Run All Cells from the
menu, waits for the ipywidgets sliders of the DW-T-Loss weight explorer (Eq. (4),
``w = (1 + eps) / (d / sigma + eps) - 1``) to render, interrupts the kernel (the training cells after
the widget would otherwise keep the kernel busy for minutes and queue the slider's update behind
them), moves the sigma slider with the keyboard and asserts that the printed weights changed.
A screenshot is saved as ``tmp_path / "jupyterlab_widget.png"``. The server (and its kernels) is
always shut down in the fixture's teardown.

Needs ``playwright`` (pinned in environment.txt) and Debian's ``chromium`` (``apt-get install -y
chromium``; ``.ci/run`` installs it). Without them the test fails, unless
``VPR_NB_ALLOW_SKIP_BROWSER=1`` is set, in which case it is skipped.
"""
from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = REPO / "notebooks"
NOTEBOOK = "03_distance_ranking_weighted_loss.ipynb"
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-quic",
                 "--no-first-run", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
TEST_BUDGET_S = 180.0          # server start to last assertion; every wait below is also cut to what is left
SERVER_START_TIMEOUT_S = 45.0
UI_TIMEOUT_MS = 30_000          # opening the notebook, menus, the interrupt
WIDGET_TIMEOUT_MS = 75_000      # imports + cells before the widget, on a loaded 2-core machine
UPDATE_TIMEOUT_MS = 30_000      # the kernel re-running the widget callback after a slider move
SHUTDOWN_TIMEOUT_S = 10.0
INTERRUPT_TRIES = 5
SKIP_ENV = "VPR_NB_ALLOW_SKIP_BROWSER"
WIDGET_CALL = "distance_weight_explorer("      # text of notebook 03's widget cell

_INSTALL_HINT = (
    "Install them with `.venv/bin/python -m pip install -r environment.txt` (playwright) and "
    "`apt-get install -y chromium` (Debian's browser at /usr/bin/chromium; do NOT run `playwright "
    "install`), or set VPR_NB_ALLOW_SKIP_BROWSER=1 to skip this test.")


def _missing_requirements() -> list[str]:
    missing = []
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        missing.append("the Python package playwright")
    if not (CHROMIUM.is_file() and os.access(CHROMIUM, os.X_OK)):
        missing.append(f"Debian's chromium at {CHROMIUM}")
    return missing


def _require_browser() -> None:
    missing = _missing_requirements()
    if not missing:
        return
    message = "the browser test needs " + " and ".join(missing) + ". "
    if os.environ.get(SKIP_ENV) == "1":
        pytest.skip(message + f"Skipped because {SKIP_ENV}=1.")
    pytest.fail(message + _INSTALL_HINT, pytrace=False)


class _Budget:
    """Wall-clock budget shared by the fixture and the test, so the whole test stays bounded."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.deadline = time.monotonic() + seconds

    def left_s(self, cap_s: float) -> float:
        left = self.deadline - time.monotonic()
        if left <= 0:
            pytest.fail(f"the browser test ran out of its {self.seconds:.0f} s budget", pytrace=False)
        return min(cap_s, left)

    def left_ms(self, cap_ms: float) -> float:
        return 1000.0 * self.left_s(cap_ms / 1000.0)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _jupyter_command() -> list[str]:
    exe = Path(sys.executable).with_name("jupyter")   # the venv's jupyter next to the venv's python
    return [str(exe), "lab"] if exe.is_file() else [sys.executable, "-m", "jupyterlab"]


def _write_json(path: Path, payload: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=1))


def _isolated_env(base: Path) -> dict:
    """Environment for the server and its kernels: every Jupyter/IPython dir under ``base``."""
    env = dict(os.environ)
    dirs = {"JUPYTER_CONFIG_DIR": "config", "JUPYTER_DATA_DIR": "data", "JUPYTER_RUNTIME_DIR": "runtime",
            "JUPYTERLAB_SETTINGS_DIR": "lab-settings", "JUPYTERLAB_WORKSPACES_DIR": "lab-workspaces",
            "IPYTHONDIR": "ipython"}
    for var, name in dirs.items():
        (base / name).mkdir(parents=True, exist_ok=True)
        env[var] = str(base / name)
    env["JUPYTER_PLATFORM_DIRS"] = "1"
    env["PYDEVD_DISABLE_FILE_VALIDATION"] = "1"
    # The kernel is this interpreter (the venv's), whatever other kernelspecs the machine has.
    _write_json(base / "data" / "kernels" / "python3" / "kernel.json",
                {"argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
                 "display_name": "Python 3 (ipykernel)", "language": "python"})
    # No "get notified about Jupyter news?" toast and no update check covering the notebook.
    _write_json(base / "lab-settings" / "@jupyterlab" / "apputils-extension" / "notification.jupyterlab-settings",
                {"fetchNews": "false", "checkForUpdates": False})
    # Render every cell (no virtualised notebook), so the widget cell is always in the DOM.
    _write_json(base / "lab-settings" / "@jupyterlab" / "notebook-extension" / "tracker.jupyterlab-settings",
                {"windowingMode": "none"})
    return env


def _api(base_url: str, token: str, path: str, method: str = "GET", timeout: float = 5.0):
    """(HTTP status, decoded JSON body or None) of a Jupyter Server REST call."""
    req = urllib.request.Request(base_url + path, method=method, data=b"" if method == "POST" else None,
                                 headers={"Authorization": f"token {token}"})
    with urllib.request.urlopen(req, timeout=timeout) as resp:
        body = resp.read()
        try:
            return resp.status, json.loads(body) if body else None
        except ValueError:
            return resp.status, None


def _kernels_idle(base_url: str, token: str, polls: int = 4, every_s: float = 0.5) -> bool:
    """True when the server reports every kernel idle on ``polls`` consecutive polls.

    A run of queued cells goes busy -> idle -> busy between cells, so one idle reading is not enough.
    """
    for i in range(polls):
        if i:
            time.sleep(every_s)
        _, kernels = _api(base_url, token, "/api/kernels")
        if not kernels or any(k.get("execution_state") != "idle" for k in kernels):
            return False
    return True


def _log_tail(log: Path, n: int = 40) -> str:
    try:
        return "\n".join(log.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return "(no server log)"


def _stop(proc: subprocess.Popen, base_url: str, token: str) -> None:
    """Shut the server and its kernels down: REST shutdown, then SIGTERM, then SIGKILL to its group."""
    if proc.poll() is None:
        try:
            _api(base_url, token, "/api/shutdown", method="POST")
        except (OSError, urllib.error.URLError):
            pass
        try:
            proc.wait(timeout=SHUTDOWN_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout=SHUTDOWN_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                pass
    # Kernels are the server's children in its own process group: make sure none outlive it.
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    if proc.poll() is None:
        proc.wait(timeout=SHUTDOWN_TIMEOUT_S)


@pytest.fixture
def lab_server(tmp_path):
    """A JupyterLab server on a temporary copy of notebooks/; yields (base_url, token, root, log, budget)."""
    _require_browser()
    budget = _Budget(TEST_BUDGET_S)
    root = tmp_path / "notebooks"
    shutil.copytree(NOTEBOOKS, root, ignore=shutil.ignore_patterns(".ipynb_checkpoints", "__pycache__"))
    env = _isolated_env(tmp_path / "jupyter")
    log = tmp_path / "jupyter-server.log"
    token = secrets.token_hex(24)
    port = _free_port()
    base_url = f"http://127.0.0.1:{port}"
    cmd = _jupyter_command() + [
        "--no-browser", "--ip=127.0.0.1", f"--port={port}", "--ServerApp.port_retries=0",
        f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={root}",
        "--LabApp.news_url=", "--ServerApp.terminals_enabled=False"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        cmd.append("--allow-root")
    with open(log, "wb") as log_file:
        proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=log_file, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + budget.left_s(SERVER_START_TIMEOUT_S)
        while True:
            if proc.poll() is not None:
                pytest.fail(f"jupyter lab exited with code {proc.returncode} before answering; "
                            f"log:\n{_log_tail(log)}", pytrace=False)
            try:
                if _api(base_url, token, "/api/status", timeout=2.0)[0] == 200:
                    break
            except (OSError, urllib.error.URLError):
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"jupyter lab did not answer on {base_url} in time; "
                            f"log:\n{_log_tail(log)}", pytrace=False)
            time.sleep(0.5)
        yield base_url, token, root, log, budget
    finally:
        _stop(proc, base_url, token)


def _widget_text(cell, timeout_ms: float) -> str:
    return cell.locator(".widget-output").first.inner_text(timeout=timeout_ms).strip()


def _click_menu(page, menu: str, item: str, timeout_ms: float) -> None:
    """Open a main-menu entry (e.g. "Run") and click the item labelled exactly ``item``."""
    page.locator(f'#jp-MainMenu .lm-MenuBar-itemLabel:text-is("{menu}")').first.click(timeout=timeout_ms)
    page.locator(f'.lm-Menu .lm-Menu-itemLabel:text-is("{item}")').first.click(timeout=timeout_ms)


@pytest.mark.slow
def test_weight_explorer_reacts_in_jupyterlab(lab_server, tmp_path, record_property):
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    base_url, token, root, log, budget = lab_server

    def ui() -> float:   # the UI timeout, cut to what is left of the test's budget
        return budget.left_ms(UI_TIMEOUT_MS)

    assert (root / NOTEBOOK).is_file(), f"{NOTEBOOK} is missing from notebooks/"
    name, call = NOTEBOOK, WIDGET_CALL
    record_property("notebook", name)
    screenshot = tmp_path / "jupyterlab_widget.png"
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS,
                                     timeout=ui())
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.set_default_timeout(UI_TIMEOUT_MS)
            try:
                page.goto(f"{base_url}/lab/tree/{name}?token={token}", wait_until="domcontentloaded",
                          timeout=ui())
                notebook = page.locator(".jp-NotebookPanel:not(.lm-mod-hidden) .jp-Notebook")
                notebook.wait_for(state="visible", timeout=ui())
                # Kernel started and idle before running (status bar: "Python 3 (ipykernel) | Idle").
                page.locator(".jp-StatusBar-Widget", has_text="Idle").first.wait_for(state="visible", timeout=ui())
                notebook.click(position={"x": 5, "y": 5}, timeout=ui())   # focus it for the menu command
                _click_menu(page, "Run", "Run All Cells", ui())

                cell = page.locator(".jp-CodeCell", has_text=call,
                                    has=page.locator(".widget-slider")).first
                handle = cell.locator(".widget-slider .noUi-handle").first
                # The slider, or fail fast on a traceback in a cell before it.
                error = page.locator(".jp-OutputArea-output", has_text="Traceback (most recent call last)")
                handle.or_(error).first.wait_for(state="visible", timeout=budget.left_ms(WIDGET_TIMEOUT_MS))
                assert error.count() == 0, f"a cell raised before the widget rendered:\n{error.first.inner_text()}"
                output = cell.locator(".widget-output", has_text="relative spread").first
                output.wait_for(state="visible", timeout=budget.left_ms(WIDGET_TIMEOUT_MS))

                # Stop the training cells queued after the widget, so the slider's update is served now
                # (an interrupt landing between two cells is ignored by the kernel: retry until idle).
                for _ in range(INTERRUPT_TRIES):
                    if _kernels_idle(base_url, token):
                        break
                    _click_menu(page, "Kernel", "Interrupt Kernel", ui())
                    page.wait_for_timeout(budget.left_ms(1000))
                else:
                    assert _kernels_idle(base_url, token), \
                        f"the kernel stayed busy after {INTERRUPT_TRIES} interrupts"

                before = _widget_text(cell, ui())
                handle.scroll_into_view_if_needed(timeout=ui())
                handle.focus(timeout=ui())
                page.keyboard.press("ArrowRight")   # sigma one step up (0.05 in log10)
                pressed = time.monotonic()
                deadline = pressed + budget.left_s(UPDATE_TIMEOUT_MS / 1000)
                after = before
                # The widget clears its output, then prints: wait for a *complete* new text that stays
                # the same for half a second, not an in-between state.
                while time.monotonic() < deadline:
                    page.wait_for_timeout(250)
                    after = _widget_text(cell, ui())
                    if after != before and _has_weight_line(after):
                        page.wait_for_timeout(500)
                        if _widget_text(cell, ui()) == after:
                            break
                waited = time.monotonic() - pressed
                cell.scroll_into_view_if_needed(timeout=ui())
                page.screenshot(path=str(screenshot), timeout=ui())
            except (PlaywrightError, AssertionError, pytest.fail.Exception) as exc:
                try:
                    page.screenshot(path=str(tmp_path / "failure.png"))
                except PlaywrightError:
                    pass
                pytest.fail(f"driving JupyterLab failed: {exc}\nscreenshot: {tmp_path / 'failure.png'}\n"
                            f"server log tail:\n{_log_tail(log)}", pytrace=False)
        finally:
            browser.close()

    assert after != before, (f"the widget output did not change within {waited:.1f} s of moving the sigma slider "
                             f"(limit {UPDATE_TIMEOUT_MS / 1000:.0f} s, or what was left of the {TEST_BUDGET_S:.0f} s "
                             f"budget): {before!r}")
    w_before, w_after = _marked_weights(before), _marked_weights(after)
    assert sorted(w_before) == sorted(w_after), f"marked distances changed: {before!r} -> {after!r}"
    # Eq. (4) with eps fixed: w(0) = 1 / eps whatever sigma, and w(d > 0) grows with sigma.
    for d, w in w_before.items():
        if d == 0.0:
            assert w_after[d] == pytest.approx(w, abs=1e-3), (before, after)
        else:
            assert w_after[d] > w, f"w({d:g} m) should grow when sigma grows: {before!r} -> {after!r}"
    assert screenshot.is_file() and screenshot.stat().st_size > 0


def _has_weight_line(text: str) -> bool:
    """Whether the explorer's output holds its full "w at ... | relative spread ..." line."""
    return any(ln.startswith("w at ") and "relative spread" in ln for ln in text.splitlines())


def _marked_weights(text: str) -> dict:
    """``{distance: weight}`` from the explorer's line "w at 0 m: 10.000, 5 m: 9.353, ... | relative spread ..."."""
    line = next((ln for ln in text.splitlines() if ln.startswith("w at ") and "relative spread" in ln), None)
    assert line is not None, f"the explorer printed no 'w at ... | relative spread' line: {text!r}"
    pairs = re.findall(r"([0-9.]+) m: (-?[0-9.]+)", line.split("|")[0])
    assert pairs, f"no 'distance m: weight' pairs in {line!r}"
    return {float(d): float(w) for d, w in pairs}
