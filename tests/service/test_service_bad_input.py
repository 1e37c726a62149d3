"""Bad input gets a clear 4xx with a message; the session keeps working and loses nothing it accepted.

Property-based: random and garbled JSON / binary blocks never produce a 5xx (HTTP) or a closed
socket (WebSocket).
"""

from __future__ import annotations

import io
import json
import struct
import zlib

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from drivers.blocks import BINARY_CONTENT_TYPE, MAGIC, SampleBlock, encode_binary, encode_json


def _json(obj) -> bytes:
    return json.dumps(obj).encode()


def _mutated(block: SampleBlock, mutate) -> bytes:
    doc = json.loads(json.dumps(encode_json(block)))
    mutate(doc)
    return json.dumps(doc).encode()  # allow_nan: NaN/Infinity literals are what a buggy robot would send


def _binary_with(block: SampleBlock, **replace) -> bytes:
    channels = {k: c for k, c in block.channels.items()}
    for kind, data in replace.items():
        old = channels[kind]
        channels[kind] = type(old)(data, old.rate_hz, old.units)
    return encode_binary(SampleBlock(block.t0, channels, block.seq))


def _set(path: list, value):
    def mutate(doc):
        node = doc
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return mutate


def _bad_requests(block: SampleBlock) -> list[tuple[str, bytes, str, int, str]]:
    """(label, body, content type, expected status, words the message must contain)."""
    nan_accel = block.channels["accel"].data.copy()
    nan_accel[3, 1] = np.nan
    inf_force = block.channels["force"].data.copy()
    inf_force[0] = np.inf
    huge_accel = block.channels["accel"].data.copy()
    huge_accel[5, 0] = 3e15  # finite in float32; it would overflow the features of every session in its batch
    return [
        ("not json", b"{seq: 1", "application/json", 400, "not valid JSON"),
        ("json array", b"[1, 2, 3]", "application/json", 422, "must be a JSON object"),
        ("no channels", _json({"seq": block.seq, "t0": 0.0}), "application/json", 422, "channels must be"),
        (
            "strings as samples",
            _mutated(block, _set(["channels", "force", "data"], ["a", "b"])),
            "application/json",
            422,
            "list of numbers",
        ),
        (
            "numbers as strings",
            _mutated(block, _set(["channels", "force", "data"], ["1.5"] * len(block.channels["force"].data))),
            "application/json",
            422,
            "list of numbers",
        ),
        (
            "booleans as samples",
            _mutated(block, _set(["channels", "speed", "data"], [True] * len(block.channels["speed"].data))),
            "application/json",
            422,
            "holds no booleans",
        ),
        (
            "JSON block too large to parse",
            _mutated(block, _set(["channels", "accel", "data"], [[0.25, -0.5, 1.0]] * 20_000)),
            "application/json",
            413,
            "send larger blocks in the binary format",
        ),
        (
            "booleans among numbers",
            _mutated(
                block, _set(["channels", "speed", "data"], [1.0, True] * (len(block.channels["speed"].data) // 2))
            ),
            "application/json",
            422,
            "holds no booleans",
        ),
        (
            "beyond any sensor",
            _binary_with(block, accel=huge_accel),
            BINARY_CONTENT_TYPE,
            422,
            "acceleration 3e+15 m/s^2 is outside its physical range",
        ),
        (
            "ragged samples",
            _mutated(block, _set(["channels", "accel", "data"], [[1, 2, 3], [1, 2]])),
            "application/json",
            422,
            "rectangular",
        ),
        (
            "accel with 2 axes",
            _mutated(block, _set(["channels", "accel", "data"], [[1.0, 2.0]] * 20)),
            "application/json",
            422,
            "accel: shape",
        ),
        (
            "NaN in JSON",
            _mutated(block, _set(["channels", "speed", "data"], [float("nan")] * 20)),
            "application/json",
            422,
            "NaN or Inf",
        ),
        ("NaN in binary", _binary_with(block, accel=nan_accel), BINARY_CONTENT_TYPE, 422, "NaN or Inf"),
        ("Inf in binary", _binary_with(block, force=inf_force), BINARY_CONTENT_TYPE, 422, "NaN or Inf"),
        (
            "absurd rate",
            _mutated(block, _set(["channels", "accel", "rate_hz"], 1e9)),
            "application/json",
            422,
            "sample rate must lie in",
        ),
        (
            "zero rate",
            _mutated(block, _set(["channels", "force", "rate_hz"], 0)),
            "application/json",
            422,
            "sample rate must lie in",
        ),
        (
            "astronomic rate",
            _mutated(block, _set(["channels", "force", "rate_hz"], 10**400)),
            "application/json",
            422,
            "force: sample rate must be a finite number",
        ),
        ("astronomic seq", _mutated(block, _set(["seq"], 10**30)), "application/json", 422, "seq must be below 2^63"),
        (
            "rate change",
            _mutated(block, _set(["channels", "speed", "rate_hz"], 2000.0)),
            "application/json",
            422,
            "rate changed",
        ),
        (
            "unknown channel",
            _mutated(block, _set(["channels", "temperature"], {"rate_hz": 10, "units": "C", "data": [1.0]})),
            "application/json",
            422,
            "unknown channel",
        ),
        (
            "unknown units",
            _mutated(block, _set(["channels", "force", "units"], "lbf")),
            "application/json",
            422,
            "units must be one of",
        ),
        ("negative seq", _mutated(block, _set(["seq"], -3)), "application/json", 422, "seq must be"),
        ("t0 not a number", _mutated(block, _set(["t0"], "noon")), "application/json", 422, "t0 must be"),
        ("deep nesting", b"[" * 100_000 + b"]" * 100_000, "application/json", 400, "not valid JSON"),
        ("bad magic", b"HLB2" + encode_binary(block)[4:], BINARY_CONTENT_TYPE, 422, "magic"),
        ("trailing bytes", encode_binary(block) + b"\0\0\0\0", BINARY_CONTENT_TYPE, 422, "trailing bytes"),
        ("truncated", encode_binary(block)[:-8], BINARY_CONTENT_TYPE, 422, "payload too short"),
        ("wrong content type", encode_binary(block), "text/plain", 415, "application/json or"),
        # a channel name UTF-8 cannot encode (a lone surrogate, legal in JSON): named in the answer, not a 500
        ("a lone surrogate", _mutated(block, _rename("force", "\ud800", 5)), "application/json", 422, "data must be a"),
        (
            "binary header: huge integer",
            _binary_header(b'{"seq": ' + b"9" * 5000 + b"}"),
            BINARY_CONTENT_TYPE,
            400,
            "not valid JSON: the binary block's header: Exceeds the limit",
        ),
        (
            "binary header: deep nesting",
            _binary_header(b"[" * 5000 + b"]" * 5000),
            BINARY_CONTENT_TYPE,
            400,
            "not valid JSON: the binary block's header: maximum recursion depth",
        ),
        (
            "binary: 2^62 rows of nothing",
            _binary_header(
                json.dumps(
                    {
                        "seq": block.seq,
                        "t0": 0.0,
                        "channels": {"accel": {"shape": [2**62, 0], "rate_hz": 1000.0, "units": "m/s^2"}},
                    }
                ).encode()
            ),
            BINARY_CONTENT_TYPE,
            422,
            "accel: shape [4611686018427387904, 0] is too large",
        ),
    ]


def _rename(old: str, new: str, data=None):
    def mutate(doc):
        doc["channels"][new] = doc["channels"].pop(old)
        if data is not None:
            doc["channels"][new]["data"] = data

    return mutate


def _binary_header(header: bytes) -> bytes:
    return MAGIC + struct.pack("<I", len(header)) + header


def test_each_bad_block_is_refused_clearly_and_nothing_accepted_is_lost(kit, server, client, library_dir):
    rec = kit.stroke_recording(library_dir, "synth_000", 2.6)
    blocks = kit.recording_blocks(rec)
    session = kit.create_session(client)
    n_bad = len(_bad_requests(blocks[0]))
    seen = set()
    for i, block in enumerate(blocks):
        if i % 4 == 2 and len(seen) < n_bad:  # a bad request carrying the next good block's seq, then that good block
            label, body, ctype, status, words = _bad_requests(block)[len(seen)]
            r = kit.post_block(client, session, body, ctype)
            assert r.status_code == status, (label, r.text)
            assert words in r.json()["detail"], (label, r.json())
            seen.add(label)
        r = kit.post_block(client, session, block)
        assert r.status_code == 202, r.text
        assert r.json()["duplicate"] is False
    assert len(seen) == n_bad, "not every bad request was sent"
    status = kit.wait_for(lambda: (s := kit.session_status(client, session))["counters"]["windows"] >= 5 and s)
    assert status["counters"]["windows"] == 5  # 2.6 s of good samples hold exactly five 0.5 s windows
    assert status["counters"]["blocks_accepted"] == len(blocks)
    assert status["counters"]["blocks_rejected"] == len(seen)
    assert status["counters"]["pipeline_errors"] == 0


def _png_header(width: int, height: int) -> bytes:
    """A PNG that declares width × height pixels but holds (almost) none: what a decompression bomb looks like."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b"")


def test_frame_pixels_reads_the_size_from_the_header_alone(kit):
    from drivers.blocks import MAX_FRAME_PIXELS
    from service.runtime import frame_pixels

    assert frame_pixels(kit.png(300)) == 300 * 300
    assert frame_pixels(_png_header(4096, 4096)) == MAX_FRAME_PIXELS  # declared, never decoded: the largest taken
    assert frame_pixels(b"\x89PNG\r\n\x1a\n garbage") == 0  # not an image: decoding says why
    with pytest.raises(ValueError, match="4097×4096 pixels; the service decodes at most 16777216"):
        frame_pixels(_png_header(4097, 4096))
    # past Pillow's own bomb limit (178956970 pixels): the same refusal, not Pillow's limit
    with pytest.raises(
        ValueError, match=r"^image: 900000000 pixels; the service decodes at most 16777216 \(4096×4096\)$"
    ):
        frame_pixels(_png_header(30_000, 30_000))


@pytest.mark.parametrize(
    "body, ctype, status, words",
    [
        (b"GIF89a not really", "image/gif", 415, "image/png or image/jpeg"),
        (b"hello", "text/plain", 415, "image/png"),
        (b"\x89PNG\r\n\x1a\n garbage", "image/png", 422, "not a readable image"),
        (100, "image/png", 422, "need at least 224"),  # an int: a real PNG of that size
        (
            _png_header(30_000, 30_000),
            "image/png",
            422,
            "frame: image: 900000000 pixels; the service decodes at most 16777216",
        ),
        (_png_header(8_000, 8_000), "image/png", 422, "8000×8000 pixels; the service decodes at most 16777216"),
        ("GIF", "image/png", 422, "the image is GIF; frames are PNG or JPEG"),  # a str: that format, labelled PNG
        ("BMP", "image/jpeg", 422, "the image is BMP; frames are PNG or JPEG"),
    ],
)
def test_bad_frames_are_refused_with_a_message(kit, client, body, ctype, status, words):
    session = kit.create_session(client)
    if isinstance(body, int):
        body = kit.png(body)
    elif isinstance(body, str):
        encoded = io.BytesIO()
        Image.new("L", (256, 256), 128).save(encoded, format=body)
        body = encoded.getvalue()
    r = client.post(
        f"/sessions/{session['session_id']}/frames",
        content=body,
        headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": ctype},
    )
    assert r.status_code == status and words in r.json()["detail"], r.text
    ok = client.post(
        f"/sessions/{session['session_id']}/frames",
        content=kit.png(256),
        headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": "image/png"},
    )
    assert ok.status_code == 202 and ok.json() == {
        "accepted": True,
        "used": False,
        "outcome": "ignored",
        "width": 256,
        "height": 256,
    }


def test_oversized_bodies_are_refused_before_they_are_read(kit, base_settings, library_dir):
    limit = 64 * 1024
    with (
        kit.running(base_settings.model_copy(update={"max_body_bytes": limit})) as srv,
        httpx.Client(base_url=srv.url, timeout=10) as client,
    ):
        session = kit.create_session(client)
        headers = {"Authorization": f"Bearer {session['robot_token']}", "Content-Type": BINARY_CONTENT_TYPE}
        declared = client.post(
            f"/sessions/{session['session_id']}/blocks", content=b"\0" * (limit + 1), headers=headers
        )
        assert declared.status_code == 413 and f"at most {limit} bytes" in declared.json()["detail"]

        def chunks():  # no Content-Length: counted while streaming
            for _ in range(8):
                yield b"\0" * (limit // 4)

        streamed = client.post(f"/sessions/{session['session_id']}/blocks", content=chunks(), headers=headers)
        assert streamed.status_code == 413
        frame = client.post(
            f"/sessions/{session['session_id']}/frames",
            content=b"\0" * (2 * limit),
            headers={**headers, "Content-Type": "image/png"},
        )
        assert frame.status_code == 413
        good = kit.recording_blocks(kit.stroke_recording(library_dir, "synth_000", 0.1))[0]
        assert kit.post_block(client, session, good).status_code == 202
        url = kit.socket_url(srv, session, "ingest")
        with connect(url, max_size=None) as ws:
            ws.send(b"\0" * (limit + 1))
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=5)
            assert ws.close_code == 1009  # message too big


# ---- property-based ----------------------------------------------------------------------------
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=6) | st.dictionaries(st.text(max_size=8), children, max_size=5),
    max_leaves=30,
)
kinds = st.sampled_from(["accel", "force", "speed", "position", "temperature", ""])
numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-(10**30), max_value=10**30))
channel_specs = st.fixed_dictionaries(
    {
        "rate_hz": numbers | st.text(max_size=4) | st.none(),
        "units": st.sampled_from(["m/s^2", "g", "N", "mm/s", "m/s", "mm", "m", "furlong", ""]) | st.none(),
        "data": st.lists(st.lists(numbers, max_size=4) | numbers, max_size=40),
    },
)
plausible_blocks = st.fixed_dictionaries(
    {
        "seq": st.integers(min_value=-5, max_value=10**6) | st.none(),
        "t0": numbers | st.none(),
        "channels": st.dictionaries(kinds, channel_specs, max_size=4),
    },
)


def _garbled_binary(header: dict, payload: bytes, length_delta: int) -> bytes:
    head = json.dumps(header).encode()
    return MAGIC + struct.pack("<I", max(0, len(head) + length_delta)) + head + payload


HEADERS = st.fixed_dictionaries(
    {
        "seq": st.integers(min_value=0, max_value=10**6),
        "t0": st.floats(min_value=0, max_value=1e6),
        "channels": st.dictionaries(
            kinds,
            st.fixed_dictionaries(
                {
                    "rate_hz": numbers,
                    "units": st.sampled_from(["m/s^2", "N", "mm/s", "mm", "x"]),
                    "shape": st.lists(st.integers(min_value=-2, max_value=70), min_size=0, max_size=3),
                }
            ),
            max_size=4,
        ),
    }
)


@pytest.fixture(scope="module")
def fuzz_session(server, kit):
    with httpx.Client(base_url=server.url, timeout=10) as c:
        r = c.post("/sessions", json={"name": "fuzz"}, headers=kit.FLEET)
        yield r.json()


@settings(
    max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture], derandomize=True
)
@given(
    body=st.one_of(
        json_values.map(lambda v: json.dumps(v).encode()),
        plausible_blocks.map(lambda v: json.dumps(v).encode()),
        st.binary(max_size=300),
    )
)
def test_garbled_json_never_yields_a_server_error(kit, server, fuzz_session, body):
    with httpx.Client(base_url=server.url, timeout=10) as client:
        r = kit.post_block(client, fuzz_session, body, "application/json")
    assert r.status_code in (202, 400, 422, 429), r.text
    assert isinstance(r.json().get("detail", ""), str)


@settings(
    max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture], derandomize=True
)
@given(
    header=HEADERS,
    payload=st.binary(max_size=2000),
    delta=st.integers(min_value=-3, max_value=3),
    raw=st.booleans(),
    junk=st.binary(max_size=64),
)
def test_garbled_binary_never_yields_a_server_error(kit, server, fuzz_session, header, payload, delta, raw, junk):
    body = (MAGIC + junk) if raw else _garbled_binary(header, payload, delta)
    with httpx.Client(base_url=server.url, timeout=10) as client:
        r = kit.post_block(client, fuzz_session, body)
    assert r.status_code in (202, 400, 422, 429), r.text  # 400: a header that is not JSON, as a JSON block's body


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture], derandomize=True)
@given(messages=st.lists(st.binary(max_size=200) | plausible_blocks.map(json.dumps), min_size=1, max_size=5))
def test_garbled_websocket_messages_are_answered_and_never_close_the_socket(kit, server, fuzz_session, messages):
    url = kit.socket_url(server, fuzz_session, "ingest")
    with connect(url) as ws:
        for message in messages:
            ws.send(message)
            ack = json.loads(ws.recv(timeout=10))
            assert set(ack) in ({"seq", "ok", "duplicate"}, {"seq", "ok", "error"})
        ws.send(b"ping?")  # still open and answering
        assert json.loads(ws.recv(timeout=10))["ok"] is False


def test_the_fuzzed_session_still_works(kit, server, client, fuzz_session, library_dir):
    """After the property tests above: a fresh stream into the same session still yields windows."""
    status = kit.session_status(client, fuzz_session)
    start = status["last_seq"] + 1
    t0 = 1e7  # after any t0 the fuzz may have had accepted: a new segment
    for block in kit.recording_blocks(kit.stroke_recording(library_dir, "synth_001", 1.0), t0=t0, seq0=start):
        r = kit.post_block(client, fuzz_session, block)
        assert r.status_code == 202, r.text
    before = status["counters"]["windows"]
    kit.wait_for(lambda: kit.session_status(client, fuzz_session)["counters"]["windows"] >= before + 2)


@pytest.mark.parametrize(
    "body, words",
    [
        (b'{"name": "x"', ["Expecting", "(char 12)"]),
        (b'{"name": "\xff\xfe"}', ["utf-8"]),
        (b'{"name": ' + b"[" * 1800 + b"]" * 1800 + b"}", ["recursion"]),
    ],
    ids=["truncated", "not UTF-8", "nested 1800 deep"],
)
def test_a_session_body_that_is_not_json_is_refused_as_a_block_would_be(kit, client, body, words):
    """400 with the reason, in the words a block that is not JSON gets. (An integer of thousands of digits does not
    fit the 4 KiB a session request may hold: refused 413 before it is parsed.)"""
    r = client.post("/sessions", content=body, headers={**kit.FLEET, "Content-Type": "application/json"})
    assert r.status_code == 400, r.text
    detail = r.json()["detail"]
    assert detail.startswith("body is not valid JSON: ") and all(w in detail for w in words), detail


@pytest.mark.parametrize(
    ("encoding", "declared", "words"),
    [
        ("PNG", "image/jpeg", "declared image/jpeg, but the bytes are a PNG (image/png)"),
        ("JPEG", "image/png", "declared image/png, but the bytes are a JPEG (image/jpeg)"),
    ],
)
def test_a_frame_labelled_with_the_other_image_type_is_refused_415_naming_both(kit, client, encoding, declared, words):
    """A PNG sent as image/jpeg (or the reverse) was decoded whatever its label: a client whose labels lie would
    go unnoticed until one of them sends a format the service cannot read."""
    session = kit.create_session(client)
    encoded = io.BytesIO()
    Image.new("RGB", (256, 256), (120, 80, 40)).save(encoded, format=encoding)
    r = client.post(
        f"/sessions/{session['session_id']}/frames",
        content=encoded.getvalue(),
        headers={"Authorization": f"Bearer {session['robot_token']}", "Content-Type": declared},
    )
    assert r.status_code == 415 and words in r.json()["detail"], r.text
    assert kit.session_status(client, session)["counters"]["frames_rejected"] == 1
