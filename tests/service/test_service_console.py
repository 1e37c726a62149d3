"""The operator console in a real headless Chromium: it connects, and its bars, bubble, chosen texture,
matches and latencies follow the window events."""

from __future__ import annotations

import json
import shutil
import threading
import time

import pytest
from websockets.sync.client import connect

from texture_library.attributes import ATTRIBUTES

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
selenium = pytest.importorskip("selenium", reason="selenium is not installed (pip install selenium)")
pytestmark = pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None,
                                reason="chromium and chromedriver are not installed (apt-get install chromium chromium-driver)")

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,900")


@pytest.fixture
def browser(tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path / 'chromium-profile'}")
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    try:
        yield driver
    finally:
        driver.quit()


def _text(driver, element_id: str) -> str:
    return driver.find_element("id", element_id).text


def _wait(driver, predicate, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            value = predicate(driver)
        except Exception:  # noqa: BLE001 - the DOM may be mid-update
            value = None
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"console did not update; connection: {_text(driver, 'conn')}")
        time.sleep(0.05)


def test_console_shows_live_ratings_texture_and_latency(kit, server, client, library_dir, browser, tmp_path):
    session = kit.create_session(client, "console test")
    sid, operator = session["session_id"], session["operator_token"]
    browser.get(f"{server.url}/console?session={sid}&token={operator}")
    _wait(browser, lambda d: _text(d, "conn") == "live")
    assert len(browser.find_elements("css selector", "#library-dots circle")) == 6  # the library, as faint dots

    # a reference subscriber sees what the page should show
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_005", 3.0))
    with connect(kit.socket_url(server, session, "events")) as ref:
        ref.recv(timeout=5)

        def stream():
            for block in blocks:
                kit.post_block(client, session, block)

        sender = threading.Thread(target=stream)
        sender.start()
        last = None
        while last is None or last["window_index"] < 5:
            event = json.loads(ref.recv(timeout=20))
            if event["type"] == "window":
                last = event
        sender.join()

    _wait(browser, lambda d: _text(d, "window") == "5")
    for attr in ATTRIBUTES:
        assert _text(browser, f"val-{attr}") == f"{last['ratings'][attr]:.1f}"
        assert _text(browser, f"conf-{attr}") == f"conf {last['confidence'][attr]:.2f}"
    assert _text(browser, "chosen") == last["chosen"]
    items = [li.text for li in browser.find_elements("css selector", "#matches li")]
    assert items == [f"{m['id']} — {m['distance']:.1f}" for m in last["matches"]]
    assert _text(browser, "lat-total") == f"{last['latency_ms']['total']:.2f}"
    assert _text(browser, "model") == "ridge-tactile"
    bubble = browser.find_element("id", "estimate-bubble")
    assert float(bubble.get_attribute("cx")) == pytest.approx(last["ratings"]["hard_soft"])
    assert float(bubble.get_attribute("cy")) == pytest.approx(-last["ratings"]["flat_bumpy"])
    highlighted = browser.find_element("css selector", f"#library-dots circle[data-id='{last['chosen']}']")
    assert highlighted.get_attribute("fill-opacity") == "1"
    browser.save_screenshot(str(tmp_path / "console.png"))
    assert (tmp_path / "console.png").stat().st_size > 10_000

    client.delete(f"/sessions/{sid}", headers={"Authorization": f"Bearer {operator}"})
    _wait(browser, lambda d: _text(d, "conn") == "ended")


def test_console_without_a_token_says_how_to_open_it(server, browser):
    browser.get(f"{server.url}/console")
    assert "session=ID&token=OPERATOR_TOKEN" in _text(browser, "conn")
