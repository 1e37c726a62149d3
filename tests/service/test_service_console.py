"""The operator console in a real headless Chromium: it connects, and its bars (with their intervals), bubble,
chosen texture, matches, latencies, out-of-distribution flag and last-minute plot follow the window events; it says
why the chosen entry is chosen and fits a 1366×768 screen; and its touch pad renders the chosen entry's served model
in an AudioWorklet (service/static/render-worklet.js) exactly as texture_library.renderer does, in all four
dimensions, loud enough to hear and never silent on a slow stroke."""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import re
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi import HTTPException, Request
from websockets.sync.client import connect

from texture_library.attributes import ATTRIBUTES
from texture_library.library import Library
from texture_library.lsf import poles_to_poly, poly_to_lsf
from texture_library.procedural import make_world
from texture_library.renderer import render_stroke
from texture_library.spectrum import arma_psd
from texture_library.vibration import VibrationModel

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
    "--autoplay-policy=no-user-gesture-required",  # a live AudioContext starts without a click
)


@pytest.fixture(scope="module")
def chromium(tmp_path_factory):
    """One Chromium for the module (starting one took seconds per test); `browser` hands it to each test."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    driver.set_script_timeout(120)
    try:
        yield driver, driver.get_window_size()
    finally:
        driver.quit()


@pytest.fixture
def browser(chromium):
    """The module's Chromium at its starting window size; the test's page is closed after it (about:blank: its
    sockets and audio end with it, as when the browser quit). The console keeps nothing in storage."""
    driver, size = chromium
    driver.set_window_size(size["width"], size["height"])
    try:
        yield driver
    finally:
        driver.get("about:blank")


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
    chosen_dot = browser.find_element("css selector", f"#library-dots circle[data-id='{last['chosen']}']")
    assert chosen_dot.get_attribute("data-chosen") == "true"
    marker = browser.find_element("id", "chosen-marker")  # the chosen entry's own symbol, on its library dot
    assert marker.get_attribute("visibility") == "visible"
    assert (
        marker.get_attribute("transform")
        == f"translate({chosen_dot.get_attribute('cx')} {chosen_dot.get_attribute('cy')})"
    )
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


# ---- the touch pad's renderer ------------------------------------------------------------------------------------
OUTPUT_RATE = 48_000  # the offline context's rate: 48 output samples per 1 kHz sample
BAND = (20.0, 500.0)


def render_model_json(model: VibrationModel, entry_id: str) -> dict:
    """The served rendering model (schema "hapticlink.render-model" v1) of `model`: the service's own document
    (texture_library.render_model) where this branch has it, else the same fields built here."""
    try:
        from texture_library.render_model import RenderModel
    except ImportError:
        pass
    else:
        return json.loads(RenderModel.from_vibration_model(entry_id, model).to_json_bytes())
    body = {
        "id": entry_id,
        "name": model.name,
        "rate_hz": float(model.rate_hz),
        "speeds_mm_s": np.asarray(model.speeds, float).tolist(),
        "forces_n": np.asarray(model.forces, float).tolist(),
        "triangles": np.asarray(model.triangles).tolist(),
        "ar_lsf": np.asarray(model.ar_lsf, float).tolist(),
        "ma_lsf": np.asarray(model.ma_lsf, float).tolist(),
        "variance": np.asarray(model.variance, float).tolist(),
        "gain": np.asarray(model.gain, float).tolist(),
        "mu": float(model.mu),
        "max_speed_mm_s": float(model.max_speed),
        "max_force_n": float(model.max_force),
        "surface": None,
        "taps": None,
    }
    version = hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]
    return {"schema": "hapticlink.render-model", "schema_version": 1, "model_version": version, **body}


def narrow_band_model(freq_hz: float, name: str) -> VibrationModel:
    """A near-sinusoid everywhere on its grid (one pole pair at radius 0.995): a signal a hard switch clicks in."""
    lsf = poly_to_lsf(poles_to_poly(np.array([freq_hz]), np.array([0.995]), 1000.0))
    return VibrationModel(
        name=name,
        speeds=np.array([0.0, 200.0, 0.0, 200.0]),
        forces=np.array([0.0, 0.0, 4.0, 4.0]),
        triangles=np.array([[0, 1, 2], [1, 3, 2]]),
        ar_lsf=np.tile(lsf, (4, 1)),
        ma_lsf=np.zeros((4, 0)),
        variance=np.full(4, 1e-3),
        gain=np.ones(4),
        mu=0.3,
        max_speed=200.0,
        max_force=4.0,
    )


@pytest.fixture
def pad_page(server, browser):
    """The console page as an operator loads it (no session needed to render offline)."""
    browser.get(f"{server.url}/console")
    _wait(browser, lambda d: d.execute_script("return typeof hapticlink === 'object'"))
    return browser


def _render_offline(driver, **options) -> tuple[np.ndarray, dict]:
    """The page's own renderer in an OfflineAudioContext: (left channel in m/s², the page's report)."""
    options.setdefault("sampleRate", OUTPUT_RATE)
    options.setdefault("full_scale", 100.0)  # m/s² at ±1: far from clipping
    result = driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "hapticlink.renderOffline(arguments[0]).then(done, (err) => done({failed: String(err)}));",
        options,
    )
    assert "failed" not in result, result["failed"]
    out = np.frombuffer(base64.b64decode(result["samples"]), np.float32).astype(float) * options["full_scale"]
    assert np.abs(out).max() < options["full_scale"], "the renderer clipped"
    return out, result


def _at_source_instants(out: np.ndarray, latency_ms: float, n: int) -> np.ndarray:
    """Back to 1 kHz: the output samples that fall on the 1 kHz stream's instants (every 48th, after the
    interpolator's delay) — with a windowed-sinc kernel (1 at 0, 0 at other integers) they are the 1 kHz samples."""
    step = OUTPUT_RATE // 1000
    start = round(latency_ms) * step
    back = out[start::step][:n]
    assert back.size == n, f"rendered {back.size} of {n} samples"
    return back


@pytest.mark.parametrize(("speed", "force"), [(120.0, 1.5), (40.0, 4.2), (500.0, 0.2), (0.0, 2.0)])
def test_pad_renderer_equals_the_python_renderer_sample_for_sample(pad_page, library_dir, speed, force):
    """Fed the same excitation, the worklet gives texture_library.synthesis.render's output to float32 precision:
    inside a triangle, and clamped beyond the grid's range (500 mm/s > 350, 0 mm/s where the variance is 0)."""
    model = Library.load(library_dir).model("synth_003")
    n = 1500
    excitation = np.random.default_rng(5).standard_normal(n + 100)
    out, report = _render_offline(
        pad_page,
        models=[{"model": render_model_json(model, "synth_003")}],
        seconds=(n + 100) / 1000,
        speed_mm_s=speed,
        force_n=force,
        excitation=excitation.tolist(),
    )
    assert report["latency_ms"] == 16 and report["errors"] == []
    assert [s["id"] for s in report["switched"]] == ["synth_003"]
    browser_1k = _at_source_instants(out, report["latency_ms"], n)
    python = render_stroke(model, np.full(n, speed), np.full(n, force), excitation=excitation[:n])
    scale = max(np.abs(python).max(), 1e-9)
    assert np.abs(browser_1k - python).max() <= 1e-5 * max(scale, 1.0), np.abs(browser_1k - python).max()
    if speed > 0:
        assert np.std(python) > 0.01  # a real signal, not two silences


HATT_MODELS = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "hatt-texnet" / "models"


@pytest.mark.shared
@pytest.mark.parametrize("texture", ["abs_plastic", "aluminum_foil"])
def test_pad_renderer_equals_the_python_renderer_on_hatt_models(pad_page, texture):
    """The same on HaTT's own models (AR order 18 and MA order 16 on a 40-point grid), at points inside the grid,
    between its rows, and beyond its range."""
    from texture_library.hatt_xml import read_model

    path = HATT_MODELS / f"{texture}.xml"
    if not path.is_file():
        pytest.skip(f"HaTT models not found at {HATT_MODELS} (needs ../shared)")
    model = read_model(path)
    for speed, force in [(80.0, 1.2), (model.max_speed * 0.63, model.max_force * 0.41), (400.0, 9.0)]:
        n = 1000
        excitation = np.random.default_rng(2).standard_normal(n + 100)
        out, report = _render_offline(
            pad_page,
            models=[{"model": render_model_json(model, texture)}],
            seconds=(n + 100) / 1000,
            speed_mm_s=speed,
            force_n=force,
            excitation=excitation.tolist(),
        )
        python = render_stroke(model, np.full(n, speed), np.full(n, force), excitation=excitation[:n])
        error = np.abs(_at_source_instants(out, report["latency_ms"], n) - python).max()
        assert error <= 1e-5 * max(np.abs(python).max(), 1.0), (speed, force, error)
        assert np.std(python) > 1e-3


def test_pad_renders_all_four_dimensions_as_the_python_renderer(pad_page):
    """A trajectory sample by sample — speed and force moving, the position going back and forth over the bumps,
    four touchdowns (two overlapping) — on a synthetic texture with bumps and taps: the worklet gives
    texture_library.renderer's output to float32 precision."""
    model = make_world(7, 0, image_size=32)[6].model
    assert model.surface is not None and model.taps is not None
    n = 1500
    t = np.arange(n) / 1000.0
    speed, force = 100 + 90 * np.sin(2 * np.pi * 1.3 * t), 1 + 0.8 * np.cos(2 * np.pi * 0.5 * t)
    position = np.cumsum(speed * np.sign(np.sin(2 * np.pi * 0.8 * t) + 1e-9)) / 1000.0
    touchdown = np.zeros(n)
    touchdown[[10, 700, 701, 1300]] = [30.0, 12.5, 80.0, 5.0]
    excitation = np.random.default_rng(6).standard_normal(n + 100)
    trajectory = {"speed_mm_s": speed.tolist(), "force_n": force.tolist(), "position_mm": position.tolist(),
                  "touchdown_mm_s": touchdown.tolist()}  # fmt: skip
    out, report = _render_offline(
        pad_page,
        models=[{"model": render_model_json(model, "synth_006")}],
        seconds=(n + 100) / 1000,
        excitation=excitation.tolist(),
        trajectory=trajectory,
    )
    assert report["errors"] == []
    python = render_stroke(model, speed, force, excitation=excitation[:n], position=position, touchdown=touchdown)
    plain = render_stroke(model, speed, force, excitation=excitation[:n])
    assert np.std(python - plain) > 0.1 * np.std(plain)  # the bumps and taps are a real part of the signal
    error = np.abs(_at_source_instants(out, report["latency_ms"], n) - python).max()
    assert error <= 1e-5 * np.abs(python).max(), error


@pytest.mark.parametrize("speed", [5.0, 8.0, 12.0, 17.0])
def test_pad_is_not_silent_at_5_mm_s_and_up(pad_page, speed):
    """A synthetic texture whose lowest grid cell has three silent corners (below 17.5 mm/s at 1 N a plain blend
    is silent): at 5 mm/s and up the pad plays it, at the console's default full scale, at the corner floor's
    level (the Python renderer's, within 1 dB)."""
    model = make_world(8, 0, image_size=32)[7].model
    seconds = 2.0
    out, report = _render_offline(
        pad_page,
        models=[{"model": render_model_json(model, "synth_007")}],
        seconds=seconds,
        speed_mm_s=speed,
        force_n=1.0,
        seed=4,
        full_scale=10.0,
    )
    n = int((seconds - 0.1) * 1000)
    played = _at_source_instants(out, report["latency_ms"], n)[300:]
    python = render_stroke(
        model, np.full(n, speed), np.ones(n), excitation=np.random.default_rng(4).standard_normal(n)
    )[300:]
    level_db = 20 * np.log10(np.sqrt(np.mean(played**2)) / 10.0)
    assert level_db > -70, level_db  # audible: the worklet's own level readout says so (not "silent")
    assert abs(20 * np.log10(np.std(played) / np.std(python))) <= 1.0


def test_pad_level_of_a_typical_stroke(pad_page):
    """A mouse stroke back and forth at 159 mm/s and 1 N (benchmarks.pad_level's, sample by sample), bumps included,
    on each of the synthetic world's 24 textures: at the console's default full scale (10 m/s²) the median texture
    peaks between −20 and −6 dBFS (the largest 100 ms RMS, as the page measures it) in the worklet's output."""
    from benchmarks.pad_level import pad_stroke

    speed, position = pad_stroke()
    n, rate = speed.size, 8000  # 8 kHz output: the same 1 kHz synthesis, six times fewer samples to bring back
    trajectory = {"speed_mm_s": speed.tolist(), "force_n": [1.0] * n, "position_mm": position.tolist()}
    peaks = {}
    for texture in make_world(24, 0, image_size=32):
        out, _ = _render_offline(
            pad_page,
            models=[{"model": render_model_json(texture.model, texture.model.name)}],
            seconds=n / 1000 + 0.05,
            sampleRate=rate,
            trajectory=trajectory,
            seed=1,
            full_scale=1000.0,  # far from clipping here; levels are read against the default, 10 m/s²
        )
        blocks = (out[int(0.2 * rate) : int(1.2 * rate)] / 10.0).reshape(-1, rate // 10)
        peaks[texture.model.name] = float(20 * np.log10(np.sqrt((blocks**2).mean(axis=1)).max()))
    print("\npad peaks, dBFS at 10 m/s²:", {k: round(v, 1) for k, v in peaks.items()})
    assert -20 <= np.median(list(peaks.values())) <= -6, peaks


def test_pad_interpolates_to_44100_hz_with_the_documented_kernel(pad_page, library_dir):
    """At 44.1 kHz (no whole number of output samples per 1 kHz sample) every output sample is the documented
    interpolation Σ x[m]·h(t − m) of the Python renderer's 1 kHz stream, t = k·1000/44100 − 16, h a sinc under a
    Kaiser window (β = 7) 16 samples wide on each side — computed here independently with numpy."""
    model = Library.load(library_dir).model("synth_003")
    rate, n, half, beta = 44_100, 600, 16, 7.0
    excitation = np.random.default_rng(8).standard_normal(n + 100)
    out, report = _render_offline(
        pad_page,
        models=[{"model": render_model_json(model, "synth_003")}],
        seconds=(n + 50) / 1000,
        sampleRate=rate,
        speed_mm_s=200.0,
        force_n=3.0,
        excitation=excitation.tolist(),
    )
    x = render_stroke(model, np.full(n + 100, 200.0), np.full(n + 100, 3.0), excitation=excitation)
    k = np.arange(int(0.05 * rate), int(n / 1000 * rate))  # past the start, where every tap has a source sample
    t = k * 1000.0 / rate - half
    taps = np.floor(t)[:, None] + np.arange(-half + 1, half + 1)[None, :]
    d = t[:, None] - taps
    kernel = np.sinc(d) * np.i0(beta * np.sqrt(np.clip(1 - (d / half) ** 2, 0, None))) / np.i0(beta)
    expected = (x[taps.astype(int)] * kernel).sum(axis=1)
    assert np.abs(out[k] - expected).max() <= 1e-4 * np.std(x), np.abs(out[k] - expected).max()


def _welch_db(x: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    from scipy.signal import welch

    freqs, psd = welch(x, fs=fs, nperseg=nperseg)
    return freqs, 10 * np.log10(psd)


def test_pad_spectrum_matches_the_python_renderer_within_1_db(pad_page, library_dir):
    """The worklet's own seeded noise, 30 s at 120 mm/s and 1.5 N rendered at 48 kHz: brought back to 1 kHz, its
    Welch spectrum is within 1 dB RMS over 20–500 Hz of the Python renderer's (same Welch) and of the exact ARMA
    spectrum; the 48 kHz output itself is within 1 dB of the exact spectrum over 20–400 Hz (the interpolator's
    pass band) and holds no images above 600 Hz."""
    from scipy.signal import resample_poly

    model = Library.load(library_dir).model("synth_003")
    speed, force, seconds, seed = 120.0, 1.5, 30, 11
    out, report = _render_offline(
        pad_page,
        models=[{"model": render_model_json(model, "synth_003")}],
        seconds=seconds + 0.05,
        speed_mm_s=speed,
        force_n=force,
        seed=seed,
    )
    n = seconds * 1000
    browser_1k = _at_source_instants(out, report["latency_ms"], n)
    python = render_stroke(
        model, np.full(n, speed), np.full(n, force), excitation=np.random.default_rng(seed).standard_normal(n)
    )
    freqs, browser_db = _welch_db(browser_1k, 1000.0, 512)
    _, python_db = _welch_db(python, 1000.0, 512)
    band = (freqs >= BAND[0]) & (freqs <= BAND[1])
    vs_python = np.sqrt(np.mean((browser_db - python_db)[band] ** 2))
    assert vs_python <= 1.0, f"browser vs Python renderer: {vs_python:.2f} dB RMS"
    # the exact spectrum; the Nyquist bin is left out: Welch's one-sided estimate does not double it
    inner = (freqs >= BAND[0]) & (freqs < BAND[1])
    exact_db = 10 * np.log10(arma_psd(model, np.array([speed]), np.array([force]), freqs[inner])[0])
    vs_exact = np.sqrt(np.mean((browser_db[inner] - exact_db) ** 2))
    assert vs_exact <= 1.0, f"browser vs exact ARMA spectrum: {vs_exact:.2f} dB RMS"
    # a standard decimator (scipy's polyphase filter) instead of the source instants: the same up to its roll-off
    freqs_d, decimated_db = _welch_db(resample_poly(out, 1, OUTPUT_RATE // 1000), 1000.0, 512)
    below = (freqs_d >= BAND[0]) & (freqs_d <= 450.0)
    exact_d = 10 * np.log10(arma_psd(model, np.array([speed]), np.array([force]), freqs_d[below])[0])
    assert np.sqrt(np.mean((decimated_db[below] - exact_d) ** 2)) <= 1.0
    # the 48 kHz signal: the same density in the pass band, nothing left of the 1 kHz images
    freqs_48, out_db = _welch_db(out, float(OUTPUT_RATE), 512 * 48)
    passband = (freqs_48 >= BAND[0]) & (freqs_48 <= 400.0)
    exact_48 = 10 * np.log10(arma_psd(model, np.array([speed]), np.array([force]), freqs_48[passband])[0])
    assert np.sqrt(np.mean((out_db[passband] - exact_48) ** 2)) <= 1.0
    power = 10 ** (out_db / 10)
    images = power[(freqs_48 > 600.0)].sum() / power[(freqs_48 >= BAND[0]) & (freqs_48 <= BAND[1])].sum()
    assert images < 1e-6, f"image power {10 * np.log10(images):.1f} dB"
    print(  # the figures behind docs/service.md's console section (pytest -s shows them)
        f"\nbrowser vs Python renderer {vs_python:.2f} dB RMS, vs exact ARMA spectrum {vs_exact:.2f} dB RMS "
        f"(Python renderer vs exact: {np.sqrt(np.mean((python_db[inner] - exact_db) ** 2)):.2f} dB); "
        f"images above 600 Hz {10 * np.log10(images):.0f} dB"
    )


def _switch_steps(out: np.ndarray, at_s: float, latency_ms: float, crossfade_ms: float) -> tuple[float, float]:
    """(largest |Δy| from 20 ms before to 20 ms after the crossfade, largest |Δy| of the 0.5 s of steady output on
    either side): the switch clicks when the first exceeds the second."""
    steps = np.abs(np.diff(out))
    start = at_s + latency_ms / 1000
    lo, hi = int((start - 0.02) * OUTPUT_RATE), int((start + crossfade_ms / 1000 + 0.02) * OUTPUT_RATE)
    before = steps[lo - OUTPUT_RATE // 2 : lo]
    after = steps[hi : hi + OUTPUT_RATE // 2]
    return float(steps[lo:hi].max()), float(max(before.max(), after.max()))


@pytest.mark.parametrize(
    ("first", "second"), [("synth_003", "synth_005"), ("synth_005", "synth_000"), ("tone_30", "tone_80")]
)
def test_pad_switch_is_crossfaded_without_a_click(pad_page, library_dir, first, second):
    """A model switch at 1 s: no output step around it larger than the signal's own sample-to-sample spread on
    either side. Two near-sinusoids (30 and 80 Hz) show that the check can fail: switched hard, they click."""
    lib = Library.load(library_dir)
    models = {i: lib.model(i) for i in lib.ids} | {
        "tone_30": narrow_band_model(30.0, "tone_30"),
        "tone_80": narrow_band_model(80.0, "tone_80"),
    }

    def switch(crossfade_ms: float) -> tuple[float, float]:
        out, report = _render_offline(
            pad_page,
            models=[
                {"model": render_model_json(models[first], first)},
                {"model": render_model_json(models[second], second), "at_s": 1.0, "crossfade_ms": crossfade_ms},
            ],
            seconds=2.0,
            speed_mm_s=150.0,
            force_n=2.0,
            seed=3,
        )
        assert [(s["id"], s["sample"]) for s in report["switched"]] == [(first, 0), (second, 1000)]
        assert np.std(out[: OUTPUT_RATE // 2]) > 1e-3 and np.std(out[-OUTPUT_RATE // 2 :]) > 1e-3
        return _switch_steps(out, 1.0, report["latency_ms"], crossfade_ms)

    around, own = switch(50.0)
    assert around <= own, f"click: step {around:.4g} m/s² against the signal's own {own:.4g}"
    if first.startswith("tone"):
        hard_around, hard_own = switch(0.0)
        assert hard_around > 2 * hard_own  # the counterfactual: without the crossfade the same check fails


def test_pad_refuses_a_bad_model_and_plays_on(pad_page, library_dir):
    """A served model that breaks its schema (an LSF outside (0, π)) is refused with the reason; the last good one
    plays on."""
    good = render_model_json(Library.load(library_dir).model("synth_003"), "synth_003")
    bad = json.loads(json.dumps(good)) | {"id": "broken"}
    bad["ar_lsf"][3][0] = 4.0
    out, report = _render_offline(
        pad_page, models=[{"model": good}, {"model": bad, "at_s": 0.3}], seconds=0.6, speed_mm_s=150.0, force_n=2.0
    )
    assert [s["id"] for s in report["switched"]] == ["synth_003"]
    assert len(report["errors"]) == 1 and "ar_lsf[3] must increase strictly inside (0, π)" in report["errors"][0]
    assert np.std(out[int(0.4 * OUTPUT_RATE) :]) > 0.05


# ---- the live console: the pad plays the chosen entry; why it is chosen; a 1366×768 screen -------------------------
BOX = "const r = arguments[0].getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom];"
SERVED_MODEL_ROUTE = re.compile(r"/library/\{[^}]+\}/model")


def _serves_models(app) -> bool:
    """Whether the service app has GET /library/{id}/model (read from its OpenAPI document)."""
    return any(SERVED_MODEL_ROUTE.fullmatch(path) for path in app.openapi()["paths"])


@pytest.fixture(scope="module")
def model_server(kit, base_settings, library_dir):
    """A server that serves rendering models: the service's GET /library/{id}/model?session= where this branch has
    it, else a test-only stand-in serving the same schema (render_model_json) behind a bearer token."""
    srv = kit.ServerThread(base_settings)
    if not _serves_models(srv.app):
        lib = Library.load(library_dir)

        async def served_model(entry_id: str, request: Request) -> dict:
            if not request.headers.get("authorization", "").startswith("Bearer "):
                raise HTTPException(401, "an operator token is required")
            if entry_id not in lib.ids:
                raise HTTPException(404, f"no library entry {entry_id!r}")
            return render_model_json(lib.model(entry_id), entry_id)

        srv.app.add_api_route("/library/{entry_id}/model", served_model, methods=["GET"])
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def _stream_until(kit, client, server, session, blocks, window_index: int) -> dict:
    """Post `blocks` while a reference subscriber listens; the window event numbered `window_index`."""
    with connect(kit.socket_url(server, session, "events")) as ref:
        ref.recv(timeout=5)
        sender = threading.Thread(target=lambda: [kit.post_block(client, session, b) for b in blocks])
        sender.start()
        last = None
        while last is None or last["window_index"] < window_index:
            event = json.loads(ref.recv(timeout=20))
            if event["type"] == "window":
                last = event
        sender.join()
    return last


def _model_fetches(driver) -> list[str]:
    """The URLs of the rendering models the page has fetched (Resource Timing)."""
    return driver.execute_script(
        "return performance.getEntriesByType('resource').map((e) => e.name).filter((u) => /\\/model(\\?|$)/.test(u))"
    )


def _stroke(driver, element, seconds: float = 1.2, step_px: int = 12, step_ms: int = 20) -> None:
    """A mouse stroke back and forth across `element` (step_px every step_ms: 600 px/s ≈ 159 mm/s), button held."""
    from selenium.webdriver.common.action_chains import ActionChains

    actions = ActionChains(driver, duration=step_ms)
    actions.move_to_element_with_offset(element, -120, 0).click_and_hold()
    x = -120
    for i in range(int(seconds * 1000 / step_ms)):
        dx = step_px if (i // 20) % 2 == 0 else -step_px
        x += dx
        actions.move_by_offset(dx, 0)
    actions.release().perform()


def test_console_pad_plays_the_chosen_texture(kit, model_server, library_dir, browser, tmp_path):
    """The newcomer's path: the console shows the chosen entry, fetches its served model once, Start sound runs a
    live AudioContext, and a mouse stroke on the pad makes the worklet play that entry at the stroke's speed."""
    import httpx

    with httpx.Client(base_url=model_server.url, timeout=10) as client:
        session = kit.create_session(client, "console pad")
        sid, operator = session["session_id"], session["operator_token"]
        browser.set_window_size(1366, 768)
        browser.get(f"{model_server.url}/console?session={sid}&token={operator}")
        _wait(browser, lambda d: _text(d, "conn") == "live")
        blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_005", 3.0))
        last = _stream_until(kit, client, model_server, session, blocks, 5)
        served = client.get(
            f"/library/{last['chosen']}/model", params={"session": sid}, headers={"Authorization": f"Bearer {operator}"}
        )
        assert served.status_code == 200, served.text
    _wait(browser, lambda d: _text(d, "window") == "5")
    chosen = _text(browser, "chosen")
    assert chosen == last["chosen"]
    browser.find_element("id", "audio-toggle").click()
    _wait(browser, lambda d: d.execute_script("return hapticlink.state().running"))
    _wait(browser, lambda d: d.execute_script("return hapticlink.state().playing") == chosen)
    assert _text(browser, "playing") == f"{chosen} (model {served.json()['model_version']})"
    _wait(browser, lambda d: _text(d, "level") == "silent")  # the worklet runs, and nobody touches the pad
    # fetched once per chosen entry and version: the page's chosen entry (a switch may still be fetching its model)
    fetches = _model_fetches(browser)
    assert fetches.count(f"{model_server.url}/library/{chosen}/model?session={sid}") == 1, fetches

    _stroke(browser, browser.find_element("id", "pad"))
    stroke = browser.execute_script("return hapticlink.state().stroke")
    assert stroke["model"] == chosen
    assert 20 < stroke["topSpeed"] < 400, stroke  # ≤ 600 px/s (≈ 159 mm/s at 0.2646 mm/px) in discrete moves
    assert stroke["peakRms"] > 1e-3, stroke  # the worklet played while the pad was stroked
    assert "top speed" in _text(browser, "stroke-summary") and "dBFS" in _text(browser, "stroke-summary")
    assert stroke["clipped"] == 0 and "clipping" not in _text(browser, "stroke-summary"), stroke  # the default is clear
    _wait(browser, lambda d: _text(d, "level") == "silent")  # released: the gate closes
    # at the slider's smallest full scale (0.1 m/s² = ±1) the same stroke clips, and the page says so
    browser.execute_script(
        "const el = document.getElementById('full-scale'); el.value = -1; el.dispatchEvent(new Event('input'));"
    )
    assert _text(browser, "full-scale-value") == "0.1"
    _stroke(browser, browser.find_element("id", "pad"))
    stroke = browser.execute_script("return hapticlink.state().stroke")
    assert stroke["clipped"] > 0, stroke
    assert "clipping" in _text(browser, "stroke-summary") and "raise full scale" in _text(browser, "stroke-summary")
    _wait(browser, lambda d: _text(d, "level") == "silent")
    browser.save_screenshot(str(tmp_path / "console-pad.png"))


def _window_event(**changes) -> dict:
    """A window event as the service sends it (docs/service.md), with `changes`."""
    ratings = {"rough_smooth": -31.2, "flat_bumpy": 8.4, "sticky_slippery": 12.9, "hard_soft": -48.0}
    event = {
        "type": "window", "session_id": "s", "window_index": 12, "t_start_s": 6.0, "t_end_s": 6.5, "block_seq": 324,
        "ratings": ratings, "raw_ratings": ratings,
        "interval": {"level": 0.9, "target": "ema", **{a: {"lo": v - 10, "hi": v + 10} for a, v in ratings.items()}},
        "out_of_distribution": False, "ood_reasons": [],
        "steadiness": dict.fromkeys(ratings, 0.9),
        "matches": [{"id": "synth_003", "distance": 14.2}, {"id": "synth_001", "distance": 15.0}],
        "chosen": "synth_003",
        "latency_ms": {"queue": 0.4, "features": 0.9, "model": 0.1, "lookup": 0.1, "total": 1.8},
        "model": "ridge-tactile", "inputs": "tactile",
    }  # fmt: skip
    return event | changes


def _show(driver, event: dict) -> None:
    """Hand `event` to the page exactly as its WebSocket handler does, and wait for it to be drawn."""
    driver.execute_script("onEvent(JSON.parse(arguments[0]))", json.dumps(event))
    _wait(driver, lambda d: _text(d, "chosen") == event["chosen"] and _text(d, "window") == str(event["window_index"]))


def test_console_says_when_hysteresis_holds_the_choice(kit, server, client, browser):
    """`selection` (rule, reason, held_by_hysteresis, switch_margin) is shown; without it, a chosen entry that is not
    the nearest is still explained as hysteresis; an older server's plain events show the nearest entry's reason."""
    session = kit.create_session(client, "console")  # the library, as any state, opens to a session's operator
    browser.get(f"{server.url}/console?session={session['session_id']}&token={session['operator_token']}")
    _wait(browser, lambda d: len(d.find_elements("css selector", "#library-dots circle")) == 6)
    keeping = "keeping synth_001: synth_003 is closer by 0.8; it must be closer by 12 (2 windows in a row) to take over"
    held = {"rule": "perceptual", "reason": keeping, "held_by_hysteresis": True, "switch_margin": 3.25}
    _show(browser, _window_event(chosen="synth_001", selection=held))
    assert _text(browser, "selection") == f"rule perceptual: {keeping}"  # the terminal's sentence, word for word
    assert browser.find_element("id", "selection").get_attribute("data-held") == "true"

    free = held | {"held_by_hysteresis": False, "switch_margin": 1.5, "reason": "the nearest entry"}
    _show(browser, _window_event(window_index=13, selection=free))
    assert (
        _text(browser, "selection")
        == "rule perceptual: the nearest entry (another entry must come 1.5 closer to take over)"
    )
    assert browser.find_element("id", "selection").get_attribute("data-held") == "false"

    _show(browser, _window_event(window_index=14, chosen="synth_001"))  # no `selection`: an older server
    assert _text(browser, "selection").startswith("keeping synth_001: synth_003 is closer, but not yet")
    _show(browser, _window_event(window_index=15, selection=None))
    assert _text(browser, "selection") == "nearest entry to the smoothed ratings"


def test_console_marks_the_estimate_and_the_chosen_entry(kit, server, client, browser):
    """The estimate and the chosen entry have their own symbols, the chosen one in none of the sticky→slippery
    colours; the legend names both."""
    session = kit.create_session(client, "console")  # the library, as any state, opens to a session's operator
    browser.get(f"{server.url}/console?session={session['session_id']}&token={session['operator_token']}")
    _wait(browser, lambda d: len(d.find_elements("css selector", "#library-dots circle")) == 6)
    _show(browser, _window_event(chosen="synth_002"))
    dot = browser.find_element("css selector", "#library-dots circle[data-id='synth_002']")
    marker = browser.find_element("id", "chosen-marker")
    assert marker.get_attribute("transform") == f"translate({dot.get_attribute('cx')} {dot.get_attribute('cy')})"
    shape = browser.find_element("css selector", "#chosen-marker path")
    ramp = {browser.execute_script("return colour(arguments[0])", v) for v in range(-100, 101, 5)}
    assert shape.get_attribute("stroke") not in ramp | {"#4cc2ff", "#8b98a5"} and shape.get_attribute("fill") == "none"
    assert _text(browser, "chosen-label") == "synth_002"
    assert browser.find_element("id", "estimate").get_attribute("visibility") == "visible"
    assert browser.find_element("id", "estimate-cross").get_attribute("transform") == "translate(-48 -8.4)"
    legend = _text(browser, "space-legend")
    assert "estimate (this session, smoothed)" in legend and "chosen entry (rendered)" in legend


def test_console_fits_1366x768_with_whole_labels(kit, server, client, library_dir, browser, tmp_path):
    """At 1366×768 the chosen model (with why), the latency panel, the touch pad and the perceptual space are all in
    the viewport without scrolling, and no label is cut."""
    session = kit.create_session(client, "console layout")
    browser.set_window_size(1366, 768)
    browser.get(f"{server.url}/console?session={session['session_id']}&token={session['operator_token']}")
    _wait(browser, lambda d: _text(d, "conn") == "live")
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_002", 3.0))
    last = _stream_until(kit, client, server, session, blocks, 4)
    _wait(browser, lambda d: int(_text(d, "window")) >= last["window_index"])
    # the longest explanation the page gives, so the layout is checked at its fullest
    keeping = (
        "keeping synth_001: synth_003 is closer by 2.4; it must be closer by 12 (2 windows in a row), or by 69.6 more "
        "in all, to take over"
    )
    held = {"rule": "perceptual", "reason": keeping, "held_by_hysteresis": True, "switch_margin": 3.25}
    later = {
        "window_index": 99,
        "provisional": True,
        "t_start_s": last["t_start_s"] + 5,
        "t_end_s": last["t_end_s"] + 5,
        "selection": held,
    }
    browser.execute_script("onEvent(JSON.parse(arguments[0]))", json.dumps(last | later))
    _wait(browser, lambda d: _text(d, "window") == "99")
    browser.execute_script("for (let i = 0; i < 40; i++) log('a status line long enough to wrap: ' + 'x'.repeat(60))")
    width, height = browser.execute_script("return [innerWidth, innerHeight]")
    assert width <= 1366 and height <= 768
    for element_id in ("chosen", "selection", "matches", "latency-panel", "lat-total", "pad", "audio-toggle", "space"):
        box = browser.execute_script(BOX, browser.find_element("id", element_id))
        assert box[0] >= 0 and box[1] >= 0 and box[2] <= width and box[3] <= height, (element_id, box, width, height)
    for panel in browser.find_elements("css selector", "main section"):  # every panel, the status log's too
        box = browser.execute_script(BOX, panel)
        label = panel.get_attribute("aria-label")
        assert box[0] >= 0 and box[1] >= 0 and box[2] <= width and box[3] <= height, (label, box, width, height)
    assert browser.execute_script("return document.scrollingElement.scrollWidth") <= width  # no sideways scrolling
    cut = browser.execute_script(
        "return [...document.querySelectorAll('.pole, .plot-label, .conf, .legend span, header span, h2')]"
        ".filter((e) => e.scrollWidth > e.clientWidth + 1 && getComputedStyle(e).display !== 'inline')"
        ".map((e) => e.textContent)"
    )
    assert cut == []
    poles = [e.text for e in browser.find_elements("css selector", ".pole")]
    assert poles == ["rough", "smooth", "flat", "bumpy", "sticky", "slippery", "hard", "soft"]
    browser.save_screenshot(str(tmp_path / "console-1366x768.png"))
    assert (tmp_path / "console-1366x768.png").stat().st_size > 10_000


@pytest.mark.slow
def test_demo_console_pad_plays_the_chosen_texture(tmp_path, kit, browser, capsys, monkeypatch, demo_small_assets):
    """`hapticlink demo` at a small size: the console URL it prints opens a page whose pad plays the entry the
    demo's session has chosen, fetched from the demo's own service. Then the demo is stopped as Ctrl-C stops it (its
    own handler: the demo runs in a thread here, where no signal reaches it; tests/demo/test_demo_run.py sends real
    signals) and ends with its summary."""
    import asyncio

    from demo.run import run_demo
    from service.app import create_app
    from service.settings import Settings

    if not _serves_models(create_app(Settings())):
        pytest.skip("this branch's service does not serve rendering models (GET /library/{id}/model)")
    assets = demo_small_assets  # as test_demo_run.py builds them (prepare_assets), once per run
    stop_handlers: list = []  # (the demo's loop, what it calls on SIGINT / SIGTERM)

    @contextlib.contextmanager
    def keep_stop_handler(handler):
        stop_handlers.append((asyncio.get_running_loop(), handler))
        yield []

    monkeypatch.setattr("demo.run.on_stop_signals", keep_stop_handler)
    capsys.readouterr()
    demo = threading.Thread(
        target=lambda: asyncio.run(
            run_demo(assets, host="127.0.0.1", port=kit.free_port(), per_texture_s=20.0, duration_s=120.0)
        ),
        daemon=True,
    )
    demo.start()
    printed = ""

    def console_url() -> str | None:
        nonlocal printed
        printed += capsys.readouterr().out
        found = re.search(r"http://\S+/console\?session=\S+&token=\S+", printed)
        return found.group(0) if found else None

    try:
        url = kit.wait_for(console_url, timeout_s=30)
        browser.set_window_size(1366, 768)
        browser.get(url)
        _wait(browser, lambda d: _text(d, "conn") == "live")
        _wait(browser, lambda d: _text(d, "chosen") not in ("", "—"))
        browser.find_element("id", "audio-toggle").click()
        _wait(browser, lambda d: d.execute_script("return hapticlink.state().playing") == _text(d, "chosen"))
        _stroke(browser, browser.find_element("id", "pad"))
        stroke = browser.execute_script("return hapticlink.state().stroke")
        assert stroke["peakRms"] > 1e-3 and stroke["topSpeed"] > 20, stroke
        assert "Start sound" in _text(browser, "pad-hint") and "stroke this pad" in _text(browser, "pad-hint")
        browser.save_screenshot(str(tmp_path / "demo-console.png"))
    finally:
        for loop, stop in stop_handlers:
            loop.call_soon_threadsafe(stop)  # a Ctrl-C: robot, feed and service stop, the summary is printed
        demo.join(timeout=60)
    assert not demo.is_alive()
    assert "demo summary: " in printed + capsys.readouterr().out


# the pad's own points, as its handlers take them: [event time, handling time, x, y] (ms, ms, CSS px, CSS px), the
# position relative to the pad where it is at that moment (its panel's text can move it mid-stroke)
_RECORD_POINTER_EVENTS = """
window.receivedPointer = [];
const pad = document.getElementById("pad");
const keep = (c, now) => {
  const r = pad.getBoundingClientRect();
  window.receivedPointer.push([c.timeStamp, now, c.clientX - r.left, c.clientY - r.top]);
};
let down = false;  // a pen's moves before it touches (hovering) are no part of the stroke
pad.addEventListener("pointerdown", e => { down = true; keep(e, performance.now()); }, true);
pad.addEventListener("pointermove", e => {
  if (!down) return;
  const now = performance.now();
  for (const c of (e.getCoalescedEvents ? e.getCoalescedEvents() : []).concat([e])) keep(c, now);
}, true);
"""


def _top_speed_bound_mm_s(received: list[list[float]], window_ms: float = 50.0, floor_ms: float = 8.0) -> float:
    """The most the pad's speed estimate (path length over the last `window_ms`, its span at least `floor_ms`)
    can read for these points, at any instant it samples: whole windows, and the stroke's first partial one."""
    points: list[tuple[float, float, float]] = []
    for stamp, handled, x, y in received:
        t = stamp if abs(stamp - handled) < 1000 else handled  # the page's own rule for a stamp off its clock
        if not points or t > points[-1][0]:
            points.append((t, x, y))
    times = np.array([p[0] for p in points])
    steps = np.hypot(np.diff([p[1] for p in points]), np.diff([p[2] for p in points]))
    # a full window ending at `now` counts the steps into every point stamped in [now - window, now]
    full = max(steps[(times[1:] >= t) & (times[1:] <= t + window_ms)].sum() / window_ms for t in times)
    first = max(steps[:k].sum() / max(times[k] - times[0], floor_ms) for k in range(1, len(times)))
    return 25.4 / 96 * 1000 * max(full, first)


@pytest.mark.parametrize(("kind", "pressure", "force"), [("pen", 0.5, 2.0), ("pen", 0.8, 3.2), ("touch", 0.5, 1.0)])
def test_pad_reads_speed_and_a_pens_pressure(server, browser, kind, pressure, force):
    """A pen's pressure sets the force (× 4 N); a finger presses with the default 1 N; the speed follows the
    stroke as the page received it (path length over 50 ms at 0.2646 mm per CSS px) and falls to 0 after it."""
    from selenium.webdriver.common.actions import interaction
    from selenium.webdriver.common.actions.action_builder import ActionBuilder
    from selenium.webdriver.common.actions.pointer_input import PointerInput

    browser.get(f"{server.url}/console")
    pad = browser.find_element("id", "pad")
    kinds = {"pen": interaction.POINTER_PEN, "touch": interaction.POINTER_TOUCH}
    builder = ActionBuilder(browser, mouse=PointerInput(kinds[kind], kind), duration=20)
    builder.pointer_action.move_to(pad, -150, 0).pointer_down(pressure=pressure)
    for _ in range(25):
        builder.pointer_action.move_by(12, 0, pressure=pressure)
    builder.pointer_action.pointer_up()
    browser.execute_script(_RECORD_POINTER_EVENTS)
    builder.perform()
    stroke = browser.execute_script("return hapticlink.state().stroke")
    assert stroke["force"] == pytest.approx(force)
    assert stroke["how"] == (f"pen, pressure {pressure:.2f}" if kind == "pen" else "touch: default force")
    # a busy host delivers the 20 ms moves late and bunched, so the bound is read from the events as delivered
    received = browser.execute_script("return window.receivedPointer")
    assert 20 < stroke["topSpeed"] <= 1.01 * _top_speed_bound_mm_s(received), (stroke, received)
    assert f"force up to {force:.1f} N" in _text(browser, "stroke-summary")
    _wait(browser, lambda d: _text(d, "pad-speed") == "0")  # the stroke has ended or stopped: speed decays to 0


def _decode_in_page(driver, payload: bytes, base: bytes | None = None) -> dict:
    """The page's own codec (service/static/model-codec.js) on a whole payload, or on a delta with its base body."""
    result = driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "const b64 = (s) => Uint8Array.from(atob(s), (c) => c.charCodeAt(0));"
        "const enc = (b) => btoa(String.fromCharCode(...b));"
        "(arguments[1] === null ? hapticlinkCodec.decode(b64(arguments[0]))"
        " : hapticlinkCodec.decodeDelta(b64(arguments[0]), b64(arguments[1])))"
        ".then((r) => done({source: r.source, model: r.model, body: enc(r.body)}), (e) => done({failed: e.message}));",
        base64.b64encode(payload).decode(),
        None if base is None else base64.b64encode(base).decode(),
    )
    return result


def test_page_decodes_models_and_deltas_as_python_does(pad_page, library_dir):
    """Python ↔ browser parity of the compact codec: a whole payload and a delta (a refit row, taps and bumps
    included) decode in the page to the documents Python decodes — grid, variance, gain, μ, taps exactly, LSFs to
    1e-12 relative (exp's last bit) — and the page's body is Python's, byte for byte (the base of the next delta)."""
    import dataclasses
    import zlib

    from texture_library import model_codec
    from texture_library.render_model import RenderModel, content_version
    from texture_library.surface import SurfaceProfile
    from texture_library.taps import TapSet

    taps = TapSet(np.array([15.0, 60.0]), np.cos(np.arange(160.0) / 5).reshape(2, 80) * 12.0)
    model = dataclasses.replace(Library.load(library_dir).model("synth_004"), taps=taps, surface=SurfaceProfile(0.2, 6))
    doc = RenderModel.from_vibration_model("session:s-1", model)
    content = doc.content()
    content["ar_lsf"][5] = (np.asarray(content["ar_lsf"][5]) * 0.995).tolist()
    content["variance"][5] *= 1.1
    envelope = {"schema": doc.schema_, "schema_version": 1, "id": doc.id}
    new = RenderModel.model_validate({**envelope, "model_version": content_version(content), **content})
    payload = model_codec.encode(doc)
    base = model_codec.body(payload)
    delta = model_codec.encode_delta(new, base)
    # …and a delta against another entry's body (a learnt model against its library prior: other lengths of id,
    # name, grid and taps, each section differenced against its own)
    prior = model_codec.body(
        model_codec.encode(RenderModel.from_vibration_model("synth_001", Library.load(library_dir).model("synth_001")))
    )
    across = model_codec.encode_delta(new, prior)
    cases = [
        (payload, None, model_codec.decode(payload), base),
        (delta, base, model_codec.decode_delta(delta, base)),
        (across, prior, model_codec.decode_delta(across, prior)),
    ]
    for sent, held, python, *_ in cases:
        page = _decode_in_page(pad_page, sent, held)
        assert "failed" not in page, page["failed"]
        source, want = python[0], json.loads(python[1].to_json_bytes())
        assert page["source"] == source and page["model"]["model_version"] == source
        for key in ("id", "name", "rate_hz", "speeds_mm_s", "forces_n", "triangles", "variance", "gain", "mu"):
            assert page["model"][key] == want[key], key
        for key in ("max_speed_mm_s", "max_force_n", "surface", "taps"):
            assert page["model"][key] == want[key], key
        for key in ("ar_lsf", "ma_lsf"):
            np.testing.assert_allclose(page["model"][key], want[key], rtol=1e-12, atol=0)
        assert base64.b64decode(page["body"]) == (base if held is None else python[2])
    assert len(delta) < len(model_codec.encode(new)) / 4
    # the page renders what it decoded (the worklet takes the document as it takes a served JSON one)
    _, report = _render_offline(pad_page, models=[{"model": _decode_in_page(pad_page, delta, base)["model"]}],
                                seconds=0.3, speed_mm_s=80.0, force_n=1.0)  # fmt: skip
    assert report["errors"] == [] and [s["id"] for s in report["switched"]] == ["session:s-1"]
    # a delta against another base, and a bad payload, are refused by name: nothing half-decoded
    other = model_codec.body(model_codec.encode(new))
    assert "made against base" in _decode_in_page(pad_page, delta, other)["failed"]
    assert "does not inflate" in _decode_in_page(pad_page, payload[:4] + b"\x00garbage")["failed"]
    assert "old layout" in _decode_in_page(pad_page, b"HLM1" + payload[4:])["failed"]
    assert "unexpected bytes" in _decode_in_page(pad_page, b"HLM3" + zlib.compress(base + b"xx"))["failed"]


def test_console_plays_a_model_pushed_on_its_socket(kit, server, client, library_dir, browser):
    """?models=push: the chosen entry's model comes on the event socket (decoded by the page) and the pad plays it;
    the page fetches no model."""
    session = kit.create_session(client, "console push")
    sid, operator = session["session_id"], session["operator_token"]
    browser.get(f"{server.url}/console?session={sid}&token={operator}&models=push")
    _wait(browser, lambda d: _text(d, "conn") == "live")
    blocks = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_005", 3.0))
    last = _stream_until(kit, client, server, session, blocks, 5)
    _wait(browser, lambda d: _text(d, "window") == "5")
    chosen = _text(browser, "chosen")
    assert chosen == last["chosen"]
    browser.find_element("id", "audio-toggle").click()
    _wait(browser, lambda d: d.execute_script("return hapticlink.state().playing") == chosen)
    version = server.app.state.service.runtime.render_models.version(chosen)
    assert _text(browser, "playing") == f"{chosen} (model {version})"
    assert _model_fetches(browser) == []
