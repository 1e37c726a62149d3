"""The operator console in a real headless Chromium: it connects, and its bars (with their intervals), bubble,
chosen texture, matches, latencies, out-of-distribution flag and last-minute plot follow the window events."""

from __future__ import annotations

import json
import re
import shutil
import threading
import time

import pytest
from websockets.sync.client import connect

from texture_library.attributes import ATTRIBUTES

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
selenium = pytest.importorskip("selenium", reason="selenium is not installed (pip install selenium)")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="chromium and chromedriver are not installed (apt-get install chromium chromium-driver)",
)

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--window-size=1280,900",
)


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
        assert _text(browser, f"steady-{attr}") == f"steady {last['steadiness'][attr]:.2f}"
        lo, hi = last["interval"][attr]["lo"], last["interval"][attr]["hi"]
        assert _text(browser, f"int-{attr}") == f"[{lo:.1f}, {hi:.1f}]"
        left, width = _band(browser, attr)
        assert left == pytest.approx(50 + lo / 2, abs=0.01) and width == pytest.approx((hi - lo) / 2, abs=0.01)
        # the last minute: one point per window so far, the band's upper edge and lower edge back
        line = browser.find_element("id", f"plot-line-{attr}").get_attribute("points").split()
        assert len(line) == 6
        assert float(line[-1].split(",")[0]) == pytest.approx(60.0) and float(line[-1].split(",")[1]) == pytest.approx(
            -last["ratings"][attr], abs=0.01
        )
        band = browser.find_element("id", f"plot-band-{attr}").get_attribute("points").split()
        assert len(band) == 12 and float(band[5].split(",")[1]) == pytest.approx(-hi, abs=0.01)
    assert _text(browser, "interval-level") == "90 %"
    assert _text(browser, "ood") == ("OUT OF DISTRIBUTION" if last["out_of_distribution"] else "in distribution")
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


def _band(driver, attr: str) -> tuple[float, float]:
    """(left %, width %) of an attribute's interval band on its bar."""
    style = driver.find_element("id", f"band-{attr}").get_attribute("style")
    left = re.search(r"left:\s*([-\d.]+)%", style)
    width = re.search(r"width:\s*([-\d.]+)%", style)
    assert left and width, style
    return float(left.group(1)), float(width.group(1))


def test_console_flags_out_of_distribution_input_and_widens_the_band(kit, server, client, library_dir, browser):
    """A tool pressed 4× harder than in training: the page says OUT OF DISTRIBUTION with the reason, and the
    bars' bands are as wide as the events' flagged intervals."""
    from texture_library.recording import Channel, Recording

    session = kit.create_session(client, "console ood")
    browser.get(f"{server.url}/console?session={session['session_id']}&token={session['operator_token']}")
    _wait(browser, lambda d: _text(d, "conn") == "live")
    rec = kit.stroke_recording(library_dir, "synth_003", 2.0)
    rec = Recording(rec.accel, Channel(rec.force.data * 4.0, rec.force.rate_hz), rec.speed)
    with connect(kit.socket_url(server, session, "events")) as ref:
        ref.recv(timeout=5)
        for block in kit.recording_blocks(rec):
            kit.post_block(client, session, block)
        last = None
        while last is None or last["window_index"] < 3:
            event = json.loads(ref.recv(timeout=20))
            if event["type"] == "window":
                last = event
    assert last["out_of_distribution"] is True
    _wait(browser, lambda d: _text(d, "window") == "3")
    assert _text(browser, "ood") == "OUT OF DISTRIBUTION"
    assert "force_out_of_range" in _text(browser, "ood-reasons")
    assert browser.find_element("id", "ood").get_attribute("data-state") == "ood"
    for attr in ATTRIBUTES:
        _, width = _band(browser, attr)
        assert width == pytest.approx((last["interval"][attr]["hi"] - last["interval"][attr]["lo"]) / 2, abs=0.01)
    # every window of the last minute is shaded as flagged in the plot
    assert len(browser.find_elements("css selector", f"#plot-ood-{ATTRIBUTES[0]} rect")) == 4


def test_console_without_a_token_says_how_to_open_it(server, browser):
    browser.get(f"{server.url}/console")
    assert "session=ID&token=OPERATOR_TOKEN" in _text(browser, "conn")
