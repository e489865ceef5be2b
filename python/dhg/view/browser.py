"""A real headless Chromium for the viewer's tests and for ``make demo``'s screenshot: Debian's
``chromium`` and ``chromium-driver`` driven by Selenium, WebGL drawn in software (SwiftShader),
since recent Chrome no longer falls back to it by itself and our machines have no GPU.
"""

from __future__ import annotations

import shutil
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "BrowserMissingError",
    "PageWatcher",
    "canvas_pixels",
    "chromium",
    "NOTIFICATIONS",
    "dismiss_notifications",
    "drawn_canvas",
    "find_chromium",
    "screenshot_session",
    "wait_for",
]

CHROMIUM_FLAGS = (
    "--headless=new",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",  # root in a container has no user namespace for the sandbox
    "--disable-dev-shm-usage",
    "--window-size=1100,720",
)


class BrowserMissingError(RuntimeError):
    """No Chromium or no chromedriver on this machine (``apt-get install chromium chromium-driver``)."""


def find_chromium() -> tuple[str, str]:
    """The paths of Chromium and its driver; raises :class:`BrowserMissingError` without them."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        raise BrowserMissingError(
            "the viewer's browser checks need Chromium and its driver: apt-get install chromium chromium-driver"
            f" (found browser {browser}, driver {driver})"
        )
    return browser, driver


@contextmanager
def chromium(width: int = 1100, height: int = 720) -> Iterator[Any]:
    """A headless Chromium (a Selenium ``WebDriver``), quit on exit."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser, driver_path = find_chromium()
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for flag in CHROMIUM_FLAGS:
        opts.add_argument(flag if not flag.startswith("--window-size") else f"--window-size={width},{height}")
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


class PageWatcher:
    """A page held open without drawing it: a WebSocket client that speaks viser's protocol
    version, as a browser tab does, and reads (and drops) everything the page sends. A page draws
    only while someone watches it; benchmarks and tests that need a watched page but not a
    browser's pixels use this (``with PageWatcher(url) as w: ...``). :attr:`messages` and
    :attr:`bytes` count what arrived."""

    def __init__(self, url: str, timeout_s: float = 10.0) -> None:
        import msgspec
        import viser
        from viser._messages import ViewerCameraMessage
        from websockets.sync.client import connect

        ws_url = url.replace("http://", "ws://", 1).replace("https://", "wss://", 1)
        self.messages = 0
        self.bytes = 0
        self._ws = connect(
            ws_url,
            subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
            max_size=None,
            open_timeout=timeout_s,
        )
        # viser counts a client as connected once it has sent its camera, as a browser does first.
        camera = ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0),
            position=(0.0, 0.0, 300.0),
            fov=1.0,
            near=0.01,
            far=1000.0,
            image_height=720,
            image_width=1100,
            look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 0.0, 1.0),
        )
        try:
            self._ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        except BaseException:
            self._ws.close()
            raise
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="page-watcher", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                m = self._ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except Exception:  # the page closed
                return
            self.messages += 1
            self.bytes += len(m)

    def close(self) -> None:
        """Closes the connection (idempotent)."""
        self._stop.set()
        try:
            self._ws.close()
        except Exception:
            pass
        self._thread.join(timeout=5.0)

    def __enter__(self) -> PageWatcher:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def wait_for(cond: Callable[[], Any], timeout_s: float, what: str) -> Any:
    """Polls ``cond`` every 0.1 s until it returns something true (or an array) and returns that; raises
    :class:`TimeoutError` naming ``what`` after ``timeout_s`` (a generous deadline)."""
    deadline = time.monotonic() + timeout_s
    last_exc: Exception | None = None
    while time.monotonic() < deadline:
        try:
            value = cond()
            if isinstance(value, np.ndarray) or value:  # an array (pixels) counts as found
                return value
        except Exception as exc:  # the page may still be loading
            last_exc = exc
        time.sleep(0.1)
    raise TimeoutError(f"{what} not seen within {timeout_s} s" + (f" (last error: {last_exc})" if last_exc else ""))


def canvas_pixels(driver: Any, out: str | Path | None = None) -> np.ndarray:
    """The page's 3D canvas as an RGB array (a screenshot of that element; saved as PNG to
    ``out`` when given)."""
    import io

    from PIL import Image
    from selenium.webdriver.common.by import By

    png = driver.find_element(By.TAG_NAME, "canvas").screenshot_as_png
    if out is not None:
        Path(out).write_bytes(png)
    with Image.open(io.BytesIO(png)) as im:
        return np.asarray(im.convert("RGB"))


def drawn_canvas(driver: Any, share: float = 0.02) -> np.ndarray | None:
    """The canvas's pixels once more than ``share`` of it is not background (the page's white)."""
    px = canvas_pixels(driver)
    return px if float(np.mean(np.any(px < 235, axis=2))) > share else None


NOTIFICATIONS = ".mantine-Notification-root"
"""CSS selector of the notifications the page's client raises (viser's, Mantine's component)."""

_NOTIFICATIONS_JS = """
const selector = arguments[0];
const open = () => Array.from(document.querySelectorAll(selector));
for (const n of open()) {
    const close = n.querySelector('.mantine-Notification-closeButton, button');
    if (close) close.click();
}
return open().length;
"""


def dismiss_notifications(driver: Any, timeout_s: float = 5.0) -> None:
    """Closes the notifications the page's client raises by itself, as a person does once they have
    read them: viser warns, for one, that WebGL is drawn in software (a lab PC without a GPU, and
    this module's Chromium), over the top left of the scene. Waits up to ``timeout_s`` for them to
    go; raises :class:`TimeoutError` if one stays."""
    wait_for(
        lambda: driver.execute_script(_NOTIFICATIONS_JS, NOTIFICATIONS) == 0,
        timeout_s,
        "the page's notifications closed",
    )


def screenshot_session(instructor_url: str, session_id: str, out: str | Path, timeout_s: float = 120.0) -> Path:
    """Opens the instructor's page, follows its link to ``session_id``'s page as a person would,
    waits for the bone and the numbers, and saves a screenshot of the whole page to ``out``."""
    from selenium.webdriver.common.by import By

    out = Path(out)
    with chromium() as driver:
        driver.get(instructor_url)
        link = wait_for(
            lambda: driver.find_element(By.ID, f"dhg-open-{session_id}").get_attribute("href"),
            timeout_s,
            f"session {session_id} on the instructor's page",
        )
        driver.get(link)
        wait_for(lambda: drawn_canvas(driver), timeout_s, "the bone drawn")
        wait_for(lambda: driver.find_elements(By.ID, "dhg-removed"), timeout_s, "the numbers")
        try:
            dismiss_notifications(driver)
        except TimeoutError:
            pass  # the picture with a notice over its corner is still the picture
        driver.save_screenshot(str(out))
    return out
