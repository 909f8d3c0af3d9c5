"""Image sizes from file headers, without decoding (tens of microseconds a file).

PNG: the signature and the IHDR chunk, and the IEND chunk at the end (a
truncated file has none). JPEG: the first start-of-frame segment, and the
end-of-image marker at the end. Other formats: Pillow's lazy `Image.open`
(header only). Every failure is a `DatasetError` naming the file.
"""

import struct
import warnings
from pathlib import Path

from ..errors import DatasetError

#: Largest image accepted (pixels): a guard against decompression bombs (a
#: 16000x16000 PNG decodes to 256 MB). 100 megapixels is above any camera a
#: calibration uses.
MAX_PIXELS = 100_000_000
#: Largest image side (pixels).
MAX_SIDE = 65535

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
# JPEG start-of-frame markers (baseline, progressive, lossless, ...); C4, C8, CC are not frames.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_size(path: Path, label: str | None = None) -> tuple[int, int]:
    """`(width, height)` of the image file `path`, read from its header.

    **Arguments:** `path`; `label`: how messages name the file (default `path`).

    Raises `DatasetError` for a missing file, a directory, a file that is not
    an image, a truncated PNG or JPEG, or one of more than `MAX_PIXELS` pixels.
    """
    label = str(path) if label is None else label
    try:
        with open(path, "rb") as f:
            head = f.read(33)
            if head.startswith(_PNG_SIGNATURE):
                size = _png(f, head, label)
            elif head.startswith(b"\xff\xd8\xff"):
                size = _jpeg(f, label)
            else:
                size = _other(path, label)
    except FileNotFoundError:
        raise DatasetError(f"{label}: image file missing") from None
    except IsADirectoryError:
        raise DatasetError(f"{label}: is a directory, not an image file") from None
    except OSError as e:
        raise DatasetError(f"{label}: cannot read the image file ({e.strerror or e})") from None
    w, h = size
    if w <= 0 or h <= 0:
        raise DatasetError(f"{label}: image header says {w}x{h} pixels")
    if w * h > MAX_PIXELS:
        raise DatasetError(
            f"{label}: image is {w}x{h} pixels ({w * h / 1e6:.0f} megapixels), more than the "
            f"{MAX_PIXELS / 1e6:.0f} megapixels jaxcal decodes"
        )
    return w, h


def _png(f, head: bytes, label: str) -> tuple[int, int]:
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise DatasetError(f"{label}: truncated or malformed PNG (no IHDR header)")
    w, h = struct.unpack(">II", head[16:24])
    f.seek(0, 2)
    if f.tell() < 33 + len(_PNG_IEND):
        raise DatasetError(f"{label}: truncated PNG (no image data)")
    f.seek(-len(_PNG_IEND), 2)
    if f.read(len(_PNG_IEND)) != _PNG_IEND:
        raise DatasetError(f"{label}: truncated PNG (the file does not end with the IEND chunk)")
    return w, h


def _jpeg(f, label: str) -> tuple[int, int]:
    f.seek(2)
    size = None
    while size is None:
        b = f.read(1)
        while b == b"\xff":  # fill bytes before a marker
            b = f.read(1)
        if not b:
            raise DatasetError(f"{label}: truncated or malformed JPEG (no frame header)")
        marker = b[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # standalone markers
            continue
        if marker in (0xD9, 0xDA):  # end of image / start of scan before any frame header
            raise DatasetError(f"{label}: malformed JPEG (no frame header before the image data)")
        raw = f.read(2)
        if len(raw) < 2:
            raise DatasetError(f"{label}: truncated JPEG")
        (length,) = struct.unpack(">H", raw)
        if length < 2:
            raise DatasetError(f"{label}: malformed JPEG (segment length {length})")
        if marker in _JPEG_SOF:
            body = f.read(5)
            if len(body) < 5:
                raise DatasetError(f"{label}: truncated JPEG")
            h, w = struct.unpack(">HH", body[1:5])
            size = (w, h)
        else:
            f.seek(length - 2, 1)
    f.seek(0, 2)
    end = f.tell()
    f.seek(max(0, end - 256))
    tail = f.read().rstrip(b"\x00\r\n ")
    if not tail.endswith(b"\xff\xd9"):
        raise DatasetError(f"{label}: truncated JPEG (the file does not end with the end-of-image marker)")
    return size


#: Formats besides PNG and JPEG that both Pillow (header) and OpenCV (pixels) read.
OTHER_FORMATS = ("BMP", "TIFF", "PPM", "WEBP")


def _other(path: Path, label: str) -> tuple[int, int]:
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        raise DatasetError(f"{label}: not a PNG or JPEG image") from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DecompressionBombWarning: our own limit applies
            with Image.open(path) as im:
                fmt, size = im.format, im.size
    except Image.DecompressionBombError:
        raise DatasetError(f"{label}: image of more than {MAX_PIXELS / 1e6:.0f} megapixels") from None
    except Exception:  # Pillow's format plugins raise many types on garbage; all mean "not an image"
        raise DatasetError(
            f"{label}: not an image file (expected PNG, JPEG or {', '.join(OTHER_FORMATS)})"
        ) from None
    if fmt not in OTHER_FORMATS:
        raise DatasetError(
            f"{label}: {fmt} images are not read (expected PNG, JPEG or {', '.join(OTHER_FORMATS)})"
        )
    return size
