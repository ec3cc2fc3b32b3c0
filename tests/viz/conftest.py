"""What the viewer's browser tests share: a free port, Debian's chromium driven by Playwright, and a patient wait."""

import shutil
import socket
import threading
import time

import pytest

CHROMIUM = shutil.which("chromium")
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_for(condition, seconds: float = 60.0, what: str = "") -> None:
    """Poll ``condition`` until it holds; fail naming ``what`` after ``seconds`` (a loaded CI machine is slow)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.1)
    pytest.fail(f"waited {seconds:.0f} s for {what}")


@pytest.fixture
def browser():
    pytest.importorskip("viser")
    playwright = pytest.importorskip("playwright.sync_api")
    if CHROMIUM is None:
        pytest.skip("Debian's chromium is not installed (.ci/run installs it)")
    with playwright.sync_playwright() as driver:
        chromium = driver.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        yield chromium
        chromium.close()


def open_page(browser, viewer, port: int, size: tuple[int, int] = (800, 600)):
    """Serve ``viewer`` (a FieldViewer) on a daemon thread, open its page in ``browser`` and wait for it to connect:
    -> (the page, the client's id)."""
    threading.Thread(target=viewer.serve_forever, daemon=True).start()
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    page.goto(f"http://127.0.0.1:{port}/")
    wait_for(lambda: len(viewer.server.get_clients()) == 1, what="the page to connect")
    return page, next(iter(viewer.server.get_clients()))
