"""``dhg view`` in a real headless Chromium (Debian's ``chromium`` and ``chromium-driver``, driven by
Selenium) against a running ``dhg-serve``, while virtual trainees drill: the page loads and draws,
the drill moves and the removed volume rises as the trainee cuts, the X-ray buttons show images,
an attempt's summary appears after a reset, and the instructor's page lists the class and opens
a trainee's page. Screenshots are kept in ``out/test-screenshots`` (``DHG_SCREENSHOTS``)."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from dhg.live.client import TraineeClient
from dhg.live.process import free_port
from dhg.view import Viewer
from dhg.view.browser import (
    NOTIFICATIONS,
    PageWatcher,
    canvas_pixels,
    chromium,
    dismiss_notifications,
    drawn_canvas,
    wait_for,
)
from support import Stylus, entry, stops_cleanly

SHOTS = Path(os.environ.get("DHG_SCREENSHOTS", Path(__file__).resolve().parents[1] / "out" / "test-screenshots"))


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with chromium() as driver:
        yield driver


@pytest.fixture(scope="module")
def shots() -> Path:
    SHOTS.mkdir(parents=True, exist_ok=True)
    return SHOTS


def _do(what: str, action) -> object:
    """Runs a browser action, again if the renderer was too busy to answer (a 2-core machine
    drawing WebGL in software); fails after a generous minute."""

    def once() -> object:
        result = action()
        return result if result is not None else True

    return wait_for(once, 60, what)


def _keep(driver, path: Path) -> None:
    """Saves a screenshot of the page for people to look at. It asserts nothing, so a renderer
    too busy to draw one in time (software WebGL on a loaded 2-core runner) costs the picture,
    not the test: the miss is printed instead. viser's notices are closed first, if they go."""
    try:
        dismiss_notifications(driver, timeout_s=10)
    except TimeoutError as exc:
        print(f"{path.name} with a notice: {exc}")
    try:
        wait_for(lambda: driver.save_screenshot(str(path)), 30, f"the screenshot {path.name}")
    except TimeoutError as exc:
        print(f"no {path.name}: {exc}")


def _number(driver, element_id: str) -> float:
    from selenium.webdriver.common.by import By

    text = driver.find_element(By.ID, element_id).text
    m = re.search(r"-?\d+(\.\d+)?", text)
    if m is None:
        raise ValueError(f"{element_id}: no number in {text!r}")
    return float(m.group(0))


def test_the_trainee_page_draws_the_bone_follows_the_drill_and_shows_xrays(server, browser, shots):
    from selenium.webdriver.common.by import By

    _, endpoint = server
    with TraineeClient(endpoint, "view-1") as c:
        a, d, q = entry(c)
        hand = Stylus(c, q)
        viewer = Viewer(endpoint, port=free_port(), session_id="view-1")
        try:
            hand.move(np.array([a - d * 3e-3]))  # outside the bone, before A
            browser.get(viewer.url)
            # viser's notice that WebGL draws in software (SwiftShader here) covers the scene's
            # corner; it is closed, as a person would, before the first picture of the canvas
            # (which the drilled one is compared with).
            notices = f"return document.querySelectorAll('{NOTIFICATIONS}').length"
            wait_for(lambda: browser.execute_script(notices), 90, "viser's software-WebGL notice")
            dismiss_notifications(browser, timeout_s=30)
            assert browser.execute_script(notices) == 0
            start = wait_for(lambda: drawn_canvas(browser), 90, "the bone drawn on the canvas")
            wait_for(lambda: browser.find_elements(By.ID, "dhg-removed"), 60, "the numbers panel")
            _do("the canvas before", lambda: canvas_pixels(browser, shots / "trainee-before.png"))
            removed_before = _number(browser, "dhg-removed")
            depth_before = _number(browser, "dhg-depth")
            assert depth_before < 0  # the tip is before A
            # The trainee drills in: the drill moves, the numbers follow, the bone is re-meshed.
            hand.move(a + d * np.linspace(-3e-3, 12e-3, 4000)[:, None])
            wait_for(hand.idle, 60, "the poses sent")
            page = viewer.pages["view-1"]
            wait_for(lambda: _number(browser, "dhg-removed") > removed_before + 1.0, 60, "the removed volume rising")
            wait_for(lambda: _number(browser, "dhg-depth") > depth_before + 5.0, 60, "the depth following the tip")
            wait_for(lambda: page.remeshed_chunks > 0, 60, "drilled chunks re-meshed")
            after = _do("the canvas after", lambda: canvas_pixels(browser, shots / "trainee-drilled.png"))
            assert after.shape == start.shape
            assert np.mean(np.abs(after.astype(int) - start.astype(int)) > 30) > 1e-4  # the drill moved
            assert page.remeshed_chunks < len(page.surfaces.all_chunks())  # never the whole volume
            _keep(browser, shots / "trainee-page.png")
            # The X-ray buttons: each shows that view of the bone as drilled now.
            for view in ("top", "front", "side"):
                _do(
                    f"a click on {view}",
                    lambda v=view: browser.find_element(By.XPATH, f"//button[normalize-space()='{v}']").click(),
                )
                wait_for(
                    lambda v=view: browser.find_elements(
                        By.XPATH, f"//*[contains(text(), '{v} view, as drilled now')]"
                    ),
                    60,
                    f"the {view} X-ray",
                )
                sizes = _do(
                    "the images' sizes",
                    lambda: browser.execute_script(
                        "return Array.from(document.images).map(i => [i.naturalWidth, i.naturalHeight])"
                    ),
                )
                assert any(w >= 50 and h >= 50 for w, h in sizes), sizes
                _keep(browser, shots / f"trainee-xray-{view}.png")
            # A reset ends the attempt: its summary (the server's metrics and the plot) shows.
            c.control("reset")
            wait_for(
                lambda: browser.find_elements(By.XPATH, "//*[contains(text(), 'the attempt that ended')]"),
                60,
                "the summary of the attempt",
            )
            _keep(browser, shots / "trainee-summary.png")
            assert page.feed.invalid == 0 and page.bone_errors == 0
        finally:
            hand.stop()
            viewer.close()


def test_the_instructor_page_lists_the_class_and_opens_a_trainee(server, browser, shots):
    from selenium.webdriver.common.by import By

    _, endpoint = server
    with TraineeClient(endpoint, "class-1") as c1, TraineeClient(endpoint, "class-2") as c2:
        hands = []
        for c in (c1, c2):
            a, d, q = entry(c)
            hands.append(Stylus(c, q))
            hands[-1].move(a + d * np.linspace(-3e-3, 4e-3, 1500)[:, None])
        viewer = Viewer(endpoint, port=free_port())
        try:
            browser.get(viewer.url)
            rows = wait_for(
                lambda: (
                    (
                        found := {
                            r.get_attribute("data-session")
                            for r in browser.find_elements(By.CSS_SELECTOR, ".dhg-session")
                        }
                    )
                    >= {"class-1", "class-2"}
                    and found
                ),
                60,
                "both trainees listed",
            )
            assert {"class-1", "class-2"} <= rows
            wait_for(
                lambda: "mm" in browser.find_element(By.CSS_SELECTOR, "[data-session='class-2']").text,
                60,
                "class-2's live state",
            )
            _keep(browser, shots / "instructor.png")
            # One click opens a trainee's own page (a new tab).
            first = browser.current_window_handle

            def click_open() -> bool:  # the list is redrawn each second: find and click in one go
                browser.find_element(By.ID, "dhg-open-class-2").click()
                return True

            wait_for(click_open, 30, "a click on class-2's link")
            wait_for(lambda: len(browser.window_handles) > 1, 30, "the trainee's page opened")
            browser.get("about:blank")  # the instructor's tab stops drawing: two software-drawn pages starve 2 cores
            opened = [h for h in browser.window_handles if h != first][0]

            def switch() -> bool:
                browser.switch_to.window(opened)
                return True

            wait_for(switch, 60, "the switch to the trainee's tab")
            assert browser.current_url.rstrip("/") == viewer.page_url("class-2")
            wait_for(lambda: drawn_canvas(browser), 90, "class-2's bone drawn")
            wait_for(lambda: "class-2" in browser.page_source, 30, "class-2's page")
            _keep(browser, shots / "instructor-opened-class-2.png")
            browser.close()
            browser.switch_to.window(first)
        finally:
            for h in hands:
                h.stop()
            viewer.close()


def test_a_page_draws_only_while_someone_watches_it(server):
    """An instructor's viewer starts a page for every session; unwatched, a page hears its streams
    but draws, re-meshes and plots nothing. A watcher (a WebSocket client that reads the page as a
    browser tab does, without drawing it) makes it draw what changed meanwhile; when the watcher
    leaves, the page stops drawing again."""
    _, endpoint = server
    with TraineeClient(endpoint, "watch-1") as c:
        a, d, q = entry(c)
        hand = Stylus(c, q)
        viewer = Viewer(endpoint, port=free_port(), session_id="watch-1")
        try:
            page = viewer.pages["watch-1"]
            hand.move(a + d * np.linspace(-3e-3, 4e-3, 1500)[:, None])
            # 2 s of states: the page's 30 Hz loop has run some 60 times meanwhile.
            wait_for(lambda: page.feed.states >= 20 and hand.idle(), 60, "the session's states heard")
            assert not page.watched
            assert page.frames == 0 and page.bone_updates == 0 and page.remeshed_chunks == 0
            assert page.watched_s == 0.0
            with PageWatcher(page.url) as watcher:
                wait_for(lambda: page.watched, 30, "the watcher connected")
                # What was drilled unwatched is drawn now: the drill, the bone as cut.
                wait_for(lambda: page.frames > 0 and page.remeshed_chunks > 0, 60, "the drill and the cut drawn")
                drawn = page.frames
                hand.move(a + d * np.linspace(4e-3, 8e-3, 800)[:, None])
                wait_for(lambda: page.frames > drawn, 60, "the drill followed")
                wait_for(lambda: watcher.messages > 0 and watcher.bytes > 0, 30, "the page's messages")
            wait_for(lambda: not page.watched, 30, "the watcher gone")
            # Three more states (0.3 s): a bone pass (every 0.25 s) begun while watched has ended.
            seen = page.feed.states
            wait_for(lambda: hand.idle() and page.feed.states >= seen + 3, 60, "the poses sent")
            frames, bone, states, watched_s = page.frames, page.bone_updates, page.feed.states, page.watched_s
            assert watched_s > 0
            hand.move(a + d * np.linspace(8e-3, 11e-3, 600)[:, None])
            wait_for(lambda: page.feed.states >= states + 10 and hand.idle(), 60, "the states of the new cut")
            assert (page.frames, page.bone_updates, page.watched_s) == (frames, bone, watched_s)
            # A drill swapped (or a path set) after the page started: the page follows it.
            assert page._info is not None and page._info["burr_radius_m"] == 1.25e-3
            c.control("set_drill", burr_radius_m=2e-3)
            wait_for(lambda: page._info["burr_radius_m"] == 2e-3, 30, "the page's info following the new drill")
        finally:
            hand.stop()
            viewer.close()


def test_the_shared_server_stops_cleanly_after_serving_the_viewers(server):
    stops_cleanly(server[0])
