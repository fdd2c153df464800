"""Reading one RGB-D frame from disk, with checks that name the file on failure.

Colour is an 8-bit PNG or JPEG; depth a 16-bit single-channel PNG. :func:`image_header` reads an
image's size and type from its header without decoding the pixels (PNG: the IHDR chunk; JPEG: the
SOF marker, through Pillow's lazy ``Image.open``), so a whole dataset is checked cheaply before any
frame is decoded. :func:`resample_rgb` maps a colour image onto the depth camera's pixel grid when
the two differ in size or intrinsics (ScanNet, RealSense).
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.sensors.camera import CameraIntrinsics

__all__ = [
    "ImageHeader",
    "image_header",
    "check_rgb_header",
    "check_depth_header",
    "read_rgb",
    "read_depth_m",
    "colour_sampling_map",
    "resample_rgb",
]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"  # PNG spec, section 5.2
JPEG_SOI = b"\xff\xd8\xff"  # JPEG start-of-image marker followed by the first marker's 0xFF
# PNG colour types (PNG spec, table 11.1) -> channels; 3 is palette-indexed (one index per pixel).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
# Pillow modes of the JPEGs it reads -> channels (8 bits each).
_JPEG_CHANNELS = {"L": 1, "RGB": 3, "CMYK": 4, "YCbCr": 3}
_DECODED_FORMATS = ["PNG", "JPEG"]
# Pillow modes converted after decoding (None: to the palette's own mode): a palette to its
# colours, as imageio did; the rest to the plain modes the readers' checks name (the header
# checks turn these away before decoding anyway).
_CONVERTED_MODES = {"P": None, "PA": "RGBA", "CMYK": "RGB", "YCbCr": "RGB", "1": "L"}


@dataclass(frozen=True)
class ImageHeader:
    """What an image's header says, read without decoding it.

    Attributes:
        format: ``"png"`` or ``"jpeg"``.
        width, height: pixels.
        channels: samples per pixel (a palette PNG counts 1).
        bits: bits per sample.
        png_colour_type: the PNG colour type (0 grey, 2 RGB, 3 palette, 4 grey+alpha, 6 RGBA); -1 for JPEG.
        jpeg_mode: Pillow's mode of a JPEG (``"RGB"``, ``"L"``, ``"CMYK"``); ``""`` for PNG.
    """

    format: str
    width: int
    height: int
    channels: int
    bits: int
    png_colour_type: int = -1
    jpeg_mode: str = ""

    @property
    def is_rgb8(self) -> bool:
        """8-bit colour with 3 or 4 channels (RGB, RGBA; YCbCr JPEGs decode to RGB)."""
        if self.format == "png":
            return self.bits == 8 and self.png_colour_type in (2, 6)
        return self.jpeg_mode in ("RGB", "YCbCr")

    @property
    def is_depth16(self) -> bool:
        """16-bit single-channel PNG (the depth encoding of every supported layout)."""
        return self.format == "png" and self.bits == 16 and self.png_colour_type == 0


def image_header(path: Path) -> ImageHeader:
    """The :class:`ImageHeader` of a PNG or JPEG file; a missing file, another format or a
    truncated header is a ``DatasetError`` naming the file."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(33)
    except FileNotFoundError:
        raise DatasetError(path, "image file not found") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read image ({exc.strerror or exc})") from None
    if head[:8] == PNG_SIGNATURE:
        if len(head) < 33 or head[12:16] != b"IHDR":
            raise DatasetError(path, "PNG file without an IHDR header (truncated?)")
        w, h, bits, ctype = struct.unpack(">IIBB", head[16:26])
        if ctype not in _PNG_CHANNELS:
            raise DatasetError(path, f"PNG has an invalid colour type {ctype}")
        return ImageHeader("png", w, h, _PNG_CHANNELS[ctype], bits, png_colour_type=ctype)
    if head[:3] == JPEG_SOI:
        try:
            with Image.open(path, formats=["JPEG"]) as im:  # lazy: parses markers up to SOF only
                w, h = im.size
                mode = im.mode
        except Exception as exc:  # Pillow raises many types (and DecompressionBombError) for bad headers
            raise DatasetError(path, f"cannot read the JPEG header ({type(exc).__name__}: {exc})") from None
        if mode not in _JPEG_CHANNELS:
            raise DatasetError(path, f"JPEG of unsupported mode {mode!r}")
        return ImageHeader("jpeg", w, h, _JPEG_CHANNELS[mode], 8, jpeg_mode=mode)
    raise DatasetError(path, "not a PNG or JPEG file")


def _where(list_file: Path | None, line: int | None) -> str:
    if list_file is None:
        return ""
    return f" ({list_file.name} line {line})" if line is not None else f" ({list_file.name})"


def _sized_header(path: Path, width: int, height: int, list_file: Path | None, line: int | None) -> ImageHeader:
    """:func:`image_header`, which must be ``width x height``."""
    hd = image_header(path)
    if (hd.width, hd.height) != (width, height):
        raise DatasetError(path, f"image is {hd.width}x{hd.height}, camera expects {width}x{height}"
                                 f"{_where(list_file, line)}")
    return hd


def check_rgb_header(path: Path, width: int, height: int, list_file: Path | None = None,
                     line: int | None = None) -> ImageHeader:
    """Header of a colour image, which must be 8-bit RGB/RGBA (PNG) or colour JPEG of ``width x height``.
    ``list_file``/``line`` (the list that named the image) are added to the error."""
    hd = _sized_header(path, width, height, list_file, line)
    if not hd.is_rgb8:
        detail = (f"bit depth {hd.bits}, colour type {hd.png_colour_type}" if hd.format == "png"
                  else f"mode {hd.jpeg_mode}")
        raise DatasetError(path, f"RGB image must be 8-bit colour PNG or JPEG ({detail}){_where(list_file, line)}")
    return hd


def check_depth_header(path: Path, width: int, height: int, list_file: Path | None = None,
                       line: int | None = None) -> ImageHeader:
    """Header of a depth image, which must be a 16-bit greyscale PNG of ``width x height``."""
    hd = _sized_header(path, width, height, list_file, line)
    if not hd.is_depth16:
        detail = (f"bit depth {hd.bits}, colour type {hd.png_colour_type}" if hd.format == "png"
                  else "a JPEG")
        raise DatasetError(path, f"depth image must be 16-bit greyscale PNG ({detail}){_where(list_file, line)}")
    return hd


def _read(path: Path) -> np.ndarray:
    """Decode a PNG or JPEG to ``[H, W]`` or ``[H, W, C]``: Pillow directly, which is a few
    milliseconds a frame cheaper than going through imageio's plugin layer."""
    if not path.is_file():
        raise DatasetError(path, "image file not found")
    try:
        with Image.open(path, formats=_DECODED_FORMATS) as im:
            if im.mode in _CONVERTED_MODES:
                im = im.convert(_CONVERTED_MODES[im.mode] or im.palette.mode)
            img = np.array(im)  # writable, as callers may expect of a decoded frame
    except Exception as exc:  # Pillow raises many types for corrupt files
        raise DatasetError(path, f"cannot decode image ({type(exc).__name__}: {exc})") from exc
    if not img.dtype.isnative:  # a big-endian 16-bit mode: native order for the checks
        img = img.astype(img.dtype.newbyteorder("="))
    return img


def read_rgb(path: Path, camera: CameraIntrinsics) -> np.ndarray:
    """RGB image ``[H, W, 3]`` uint8 (PNG or JPEG); an alpha channel is dropped."""
    img = _read(path)
    if img.ndim != 3 or img.shape[2] not in (3, 4) or img.dtype != np.uint8:
        raise DatasetError(path, f"expected an 8-bit RGB image, got shape {img.shape} dtype {img.dtype}")
    if img.shape[:2] != (camera.height, camera.width):
        raise DatasetError(
            path, f"image is {img.shape[1]}x{img.shape[0]}, camera expects {camera.width}x{camera.height}"
        )
    return np.ascontiguousarray(img[..., :3])


def read_depth_m(path: Path, camera: CameraIntrinsics, allow_empty: bool = False,
                 invalid_raw: tuple[int, ...] = ()) -> np.ndarray:
    """Depth image ``[H, W]`` float32 in metres (0 = no reading).

    ``invalid_raw``: raw values that also mean "no reading" (7-Scenes: 65535); they become 0.

    Raises DatasetError for a wrong size or type, or an image with no valid pixel at all (a
    sensor dropout that would otherwise poison tracking silently) unless ``allow_empty``.
    """
    raw = _read(path)
    if raw.ndim != 2 or raw.dtype not in (np.uint16, np.int32, np.uint32):
        raise DatasetError(path, f"expected a 16-bit single-channel depth image, got shape {raw.shape} dtype {raw.dtype}")
    if raw.shape != (camera.height, camera.width):
        raise DatasetError(
            path, f"image is {raw.shape[1]}x{raw.shape[0]}, camera expects {camera.width}x{camera.height}"
        )
    if invalid_raw:
        raw = np.where(np.isin(raw, np.asarray(invalid_raw, dtype=raw.dtype)), raw.dtype.type(0), raw)
    if not allow_empty and not np.any(raw):
        raise DatasetError(path, "depth image has no valid pixel (all zero)")
    return raw.astype(np.float32) / np.float32(camera.depth_scale)


# ---- colour onto the depth camera ---------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _sampling_map(src: tuple, dst: tuple) -> tuple[np.ndarray, np.ndarray]:
    fxs, fys, cxs, cys = src
    fxd, fyd, cxd, cyd, w, h = dst
    u = np.arange(w, dtype=np.float64)
    v = np.arange(h, dtype=np.float64)
    # K_src K_dst^-1 [u v 1]^T for two pinholes without skew: an axis-aligned affine map.
    x = (fxs / fxd) * (u - cxd) + cxs  # [W]
    y = (fys / fyd) * (v - cyd) + cys  # [H]
    xs = np.broadcast_to(x[None, :], (h, w)).astype(np.float32)
    ys = np.broadcast_to(y[:, None], (h, w)).astype(np.float32)
    xs.flags.writeable = False
    ys.flags.writeable = False
    return xs, ys


def colour_sampling_map(colour: CameraIntrinsics, depth: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """For each depth pixel ``(u, v)``, the colour pixel ``K_colour K_depth^-1 [u v 1]`` as
    ``(x [H, W], y [H, W])`` float32 (pixel centres at integer coordinates).

    Valid for registered cameras only: same optical centre and orientation, differing in
    intrinsics and size (ScanNet exports, RealSense aligned streams). Lens distortion is ignored.
    """
    return _sampling_map((colour.fx, colour.fy, colour.cx, colour.cy),
                         (depth.fx, depth.fy, depth.cx, depth.cy, depth.width, depth.height))


def resample_rgb(rgb: np.ndarray, colour: CameraIntrinsics, depth: CameraIntrinsics) -> np.ndarray:
    """Colour ``[Hc, Wc, 3]`` uint8 seen by ``colour`` resampled onto ``depth``'s pixel grid:
    ``[H, W, 3]`` uint8, bilinear; depth pixels whose ray leaves the colour image are black."""
    if (colour.width, colour.height, colour.fx, colour.fy, colour.cx, colour.cy) == (
            depth.width, depth.height, depth.fx, depth.fy, depth.cx, depth.cy):
        return rgb
    hc, wc = rgb.shape[:2]
    x, y = colour_sampling_map(colour, depth)
    inside = (x >= -0.5) & (x <= wc - 0.5) & (y >= -0.5) & (y <= hc - 0.5)  # [H, W]
    x = np.clip(x, 0.0, wc - 1.0)
    y = np.clip(y, 0.0, hc - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int32), max(wc - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int32), max(hc - 2, 0))
    x1 = np.minimum(x0 + 1, wc - 1)
    y1 = np.minimum(y0 + 1, hc - 1)
    ax = (x - x0)[..., None]  # [H, W, 1]
    ay = (y - y0)[..., None]
    src = rgb.astype(np.float32)
    top = src[y0, x0] * (1 - ax) + src[y0, x1] * ax
    bottom = src[y1, x0] * (1 - ax) + src[y1, x1] * ax
    out = top * (1 - ay) + bottom * ay
    out[~inside] = 0.0
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
