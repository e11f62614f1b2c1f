"""Image file I/O and visualisation helpers."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
import torch
from PIL import Image

from uw3dgs.utils.images import ImageReadError, read_image, write_image
from uw3dgs.utils.visualize import SEPARATOR_PX, apply_colormap, depth_to_image, image_grid, to_uint8


def write_png16_rgb(path, pixels: np.ndarray) -> None:
    """Minimal 16-bit RGB PNG writer (Pillow cannot write one)."""
    height, width, _ = pixels.shape
    raw = b"".join(b"\x00" + row.astype(">u2").tobytes() for row in pixels)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0)
    chunks = chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunks)


def test_write_read_round_trip(tmp_path):
    img = torch.rand(13, 17, 3, generator=torch.Generator().manual_seed(0))
    path = tmp_path / "out" / "render.png"
    write_image(path, img)
    back = read_image(path)
    assert back.dtype == torch.float32 and back.shape == (13, 17, 3)
    torch.testing.assert_close(back, torch.from_numpy(to_uint8(img)).float() / 255, rtol=0, atol=1e-7)
    assert (back - img).abs().max() <= 0.5 / 255 + 1e-6
    # Overwriting works and leaves no temporary files behind.
    write_image(path, np.zeros((13, 17, 3), dtype=np.float32))
    assert read_image(path).max() == 0
    assert [p.name for p in path.parent.iterdir()] == ["render.png"]


def test_write_image_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="PNG"):
        write_image(tmp_path / "x.jpg", torch.zeros(4, 4, 3))
    with pytest.raises(ValueError, match="H, W, 3"):
        write_image(tmp_path / "x.png", torch.zeros(4, 4))
    assert list(tmp_path.iterdir()) == []


def test_read_grayscale_rgba_and_jpeg(tmp_path):
    gray = np.arange(20, dtype=np.uint8).reshape(4, 5) * 12
    Image.fromarray(gray).save(tmp_path / "gray.png")
    back = read_image(tmp_path / "gray.png")
    assert back.shape == (4, 5, 3)
    for c in range(3):
        np.testing.assert_allclose(back[..., c].numpy(), gray / 255.0, rtol=0, atol=1e-7)

    rgba = np.zeros((3, 3, 4), dtype=np.uint8)
    rgba[..., :3] = 200
    rgba[..., 3] = 0  # fully transparent: colours must be kept, not composited onto a background
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    np.testing.assert_allclose(read_image(tmp_path / "rgba.png").numpy(), 200 / 255.0, rtol=0, atol=1e-7)

    Image.fromarray(np.full((8, 8, 3), 100, dtype=np.uint8)).save(tmp_path / "flat.jpg", quality=95)
    jpg = read_image(tmp_path / "flat.jpg")
    assert jpg.shape == (8, 8, 3)
    assert (jpg - 100 / 255.0).abs().max() < 3 / 255.0


def test_read_16_bit_png(tmp_path):
    gray = np.array([[0, 1, 300], [32768, 65534, 65535]], dtype=np.uint16)
    Image.fromarray(gray).save(tmp_path / "gray16.png")
    back = read_image(tmp_path / "gray16.png")
    np.testing.assert_allclose(back[..., 1].numpy(), gray / 65535.0, rtol=0, atol=1e-7)

    rgb = np.array([[[0, 1000, 65535], [40000, 20000, 5]]], dtype=np.uint16)
    write_png16_rgb(tmp_path / "rgb16.png", rgb)
    # Pillow decodes 16-bit RGB at 8-bit precision; the range must still be [0, 1], not /255 of 16 bits.
    back = read_image(tmp_path / "rgb16.png")
    np.testing.assert_allclose(back.numpy(), rgb / 65535.0, rtol=0, atol=1 / 255)


def test_truncated_corrupt_and_missing_files_raise_image_read_error(tmp_path):
    noise = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    Image.fromarray(noise).save(tmp_path / "full.png")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut_0042.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageReadError, match="cut_0042.png.*truncated or corrupt"):
        read_image(tmp_path / "cut_0042.png")

    (tmp_path / "junk.png").write_bytes(b"this is not an image")
    with pytest.raises(ValueError, match="junk.png"):  # ImageReadError is a ValueError
        read_image(tmp_path / "junk.png")

    with pytest.raises(ImageReadError, match="nowhere.png.*check the path"):
        read_image(tmp_path / "nowhere.png")


def test_colormap_range_and_invalid_pixels():
    x = torch.linspace(0, 1, 12).reshape(3, 4)  # x[0, 0] = 0 < vmin, x[2, 3] = 1 > vmax
    x[0, 1], x[0, 2], x[1, 1] = float("inf"), float("nan"), -float("inf")
    mask = torch.ones(3, 4, dtype=torch.bool)
    mask[2, 2] = False
    rgb = apply_colormap(x, vmin=0.2, vmax=0.8, mask=mask)
    assert rgb.shape == (3, 4, 3) and rgb.dtype == torch.float32
    assert rgb.min() >= 0 and rgb.max() <= 1
    for pixel in [(0, 1), (0, 2), (1, 1), (2, 2)]:
        assert (rgb[pixel] == 0).all()
    # Values outside [vmin, vmax] clip to the end colours.
    ends = apply_colormap(torch.tensor([[0.2, 0.8]]), vmin=0.2, vmax=0.8)
    torch.testing.assert_close(rgb[0, 0], ends[0, 0])
    torch.testing.assert_close(rgb[2, 3], ends[0, 1])
    assert not torch.allclose(ends[0, 0], ends[0, 1])


def test_colormap_default_range_ignores_outliers():
    x = torch.linspace(0, 1, 1000).reshape(10, 100)
    x[0, 0] = 1e6
    rgb = apply_colormap(x)
    explicit = apply_colormap(x, vmin=float(np.percentile(x.numpy(), 1)), vmax=float(np.percentile(x, 99)))
    torch.testing.assert_close(rgb, explicit)
    assert len({tuple(c) for c in (rgb.reshape(-1, 3) * 20).round().tolist()}) > 10  # not squeezed

    all_invalid = apply_colormap(torch.full((2, 2), float("nan")))
    assert (all_invalid == 0).all()


def test_depth_to_image_near_is_warm_and_empty_is_black():
    depth = torch.tensor([[1.0, 2.0, 3.0, float("inf")], [4.0, 5.0, 0.0, 6.0]])
    alpha = torch.ones(2, 4)
    alpha[1, 3] = 0.1
    rgb = depth_to_image(depth, alpha)
    ends = apply_colormap(torch.tensor([[0.0, 1.0]]), vmin=0.0, vmax=1.0)
    torch.testing.assert_close(rgb[0, 0], ends[0, 1])  # nearest -> top (red) end
    torch.testing.assert_close(rgb[1, 1], ends[0, 0])  # farthest valid -> bottom (blue) end
    assert rgb[0, 0, 0] > 3 * rgb[0, 0, 2]  # warm
    for pixel in [(0, 3), (1, 2), (1, 3)]:  # open water, zero depth, low opacity
        assert (rgb[pixel] == 0).all()


def test_to_uint8():
    img = np.array([[[0.0, 1.0, 0.5], [-0.3, 1.7, np.nan]]], dtype=np.float32)
    out = to_uint8(img)
    assert out.dtype == np.uint8
    assert out.tolist() == [[[0, 255, 128], [0, 255, 0]]]
    assert to_uint8(torch.from_numpy(img)).tolist() == out.tolist()


def test_image_grid_layout():
    tiles = [torch.full((4, 5, 3), v) for v in (0.1, 0.2, 0.3)]
    grid = image_grid(tiles, ncols=2)
    assert grid.shape == (2 * 4 + SEPARATOR_PX, 2 * 5 + SEPARATOR_PX, 3)
    assert (grid[:4, :5] == 0.1).all() and (grid[:4, 5 + SEPARATOR_PX :] == 0.2).all()
    assert (grid[4 + SEPARATOR_PX :, :5] == 0.3).all()
    assert (grid[4 : 4 + SEPARATOR_PX] == 1).all() and (grid[4 + SEPARATOR_PX :, 5:] == 1).all()
    assert image_grid(tiles).shape == (4, 3 * 5 + 2 * SEPARATOR_PX, 3)
    with pytest.raises(ValueError, match="one size"):
        image_grid([torch.zeros(4, 5, 3), torch.zeros(4, 6, 3)])


def test_a_labelled_row_is_written_as_drawn(tmp_path):
    """`labelled_row` returns uint8 pixels; `write_image` keeps them (read as [0, 1] floats they clipped to white, and
    every `compare` image of uw-eval was white but its zeros)."""
    from uw3dgs.utils.video import labelled_row

    g = torch.Generator().manual_seed(0)
    tiles = [torch.rand(12, 10, 3, generator=g) for _ in range(2)]
    frame = labelled_row(tiles, ["photo", "UWI"])
    write_image(tmp_path / "compare.png", frame)
    written = np.asarray(Image.open(tmp_path / "compare.png"))
    np.testing.assert_array_equal(written, frame)
    np.testing.assert_array_equal(written[-12:, :10], to_uint8(tiles[0]))  # the first tile's pixels, under the label
