"""The load generator labels its camera frames by their bytes, as the service checks them."""

from __future__ import annotations

import io

import pytest
from PIL import Image

from benchmarks.loadgen import frame_content_type


@pytest.mark.parametrize(("encoding", "kind"), [("PNG", "image/png"), ("JPEG", "image/jpeg")])
def test_a_frame_is_labelled_by_its_bytes(encoding, kind):
    """Every frame went as image/png: a library whose photos are JPEG had each one refused (415)."""
    encoded = io.BytesIO()
    Image.new("RGB", (32, 32), (120, 80, 40)).save(encoded, format=encoding)
    assert frame_content_type(encoded.getvalue()) == kind


def test_a_frame_neither_png_nor_jpeg_is_refused_before_it_is_sent():
    with pytest.raises(ValueError, match="PNG or a JPEG"):
        frame_content_type(b"GIF89a not a frame")
