"""Image reads: bounded in memory, 16-bit PNGs scaled, decompression bombs refused with the file named."""
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from vpr_nb import datasets as D
from vpr_nb.datasets import images as I


def _png_header(path, width, height):
    """A PNG whose header says width x height (8-bit gray) but whose data is a few bytes: opening it
    costs nothing, decoding it fails (truncated), so a refusal naming the size proves nothing was decoded."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def test_a_decompression_bomb_through_image_array_names_the_file(tmp_path):
    bomb = _png_header(tmp_path / "bomb.png", 20000, 20000)          # 400 MP: Pillow's own refusal
    with pytest.raises(ValueError, match=r"bomb\.png: Pillow refuses to decode it as a possible decompression bomb"):
        D.ImageArray([bomb], (8, 8))[0]


def test_an_image_above_the_pixel_limit_is_refused_before_decoding(tmp_path):
    big = _png_header(tmp_path / "big.png", 12000, 12000)            # 144 MP in a 100-byte file
    with pytest.warns(Image.DecompressionBombWarning):                # Pillow's warning stays; the read is refused
        with pytest.raises(ValueError, match=r"big\.png: 12000x12000 pixels \(144\.0 MP\) is more than "
                                             r"vpr_nb\.datasets\.images\.MAX_IMAGE_PIXELS \(25 MP\), so it is not decoded"):
            D.read_image(big, size=(32, 48))
    small = _png_header(tmp_path / "small.png", 4000, 4000)          # within the limit: decoded, so truncated
    with pytest.raises(ValueError, match=r"cannot read image .*small\.png"):
        D.read_image(small)
    with pytest.warns(Image.DecompressionBombWarning):
        (bad,) = D.find_unreadable_images([big])
    assert "MAX_IMAGE_PIXELS" in bad[1]


def test_a_large_jpeg_read_with_a_size_is_decoded_at_reduced_scale(tmp_path, monkeypatch):
    path = tmp_path / "wide.jpg"
    Image.fromarray(np.full((300, 400, 3), (200, 40, 90), np.uint8)).save(path, quality=95)
    monkeypatch.setattr(I, "MAX_IMAGE_PIXELS", 10_000)               # 400x300 = 120 000 pixels: "too large"
    x = D.read_image(path, size=(32, 48), normalize=False)           # drafted to 1/4 scale (100x75): allowed
    assert tuple(x.shape) == (3, 32, 48)
    np.testing.assert_allclose(x.mean(dim=(1, 2)).numpy(), np.array([200, 40, 90]) / 255, atol=0.03)
    with pytest.raises(ValueError, match=r"wide\.jpg: 400x300 pixels .* or read it with a size="):
        D.read_image(path)


def test_a_16_bit_grayscale_png_is_scaled_not_clipped(tmp_path):
    ramp = np.linspace(0, 65535, 8 * 12).reshape(8, 12).astype(np.uint16)
    path = tmp_path / "depth16.png"
    Image.fromarray(ramp).save(path)
    assert Image.open(path).mode.startswith("I")
    x = D.read_image(path, normalize=False)
    assert tuple(x.shape) == (3, 8, 12)
    np.testing.assert_allclose(x[0].numpy(), ramp / 65535.0, atol=1e-6)
    assert (x[0] == x[2]).all() and 0.45 < float(x.mean()) < 0.55      # not all white
    arr = D.ImageArray([path], (8, 12))[0]
    np.testing.assert_array_equal(arr[..., 1], np.round(ramp / 65535.0 * 255).astype(np.uint8))
