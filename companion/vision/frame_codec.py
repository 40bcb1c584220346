"""Byte codec of :class:`~companion.vision.frame.CameraFrame`: a typed, versioned header and an encoded image
(the payload of ``<prefix>/camera/<vehicle>/image``).

Layout (little-endian)::

    b"ASKC" | wire version u8 | header version u8 | image format u8 | pixel encoding u8
    | vehicle u16 | seq u32 | t_capture_s f64 | t_available_s f64 | width u16 | height u16
    | fx fy cx cy f64 x 4 | n_dist u8 | dist f64 x n_dist | name length u8 | name (ASCII)
    | image length u32 | image bytes

Image formats: ``raw`` (the pixels as they are, row-major; numpy only), ``png`` (lossless) and
``jpeg`` (lossy, ``quality``) through ``cv2.imencode`` / ``cv2.imdecode`` (OpenCV: the ``vision``
extra, imported only for those two).

:func:`decode_frame` trusts nothing: magic, both versions, the enums, the exact total length,
finite numbers, the name's characters, the image's size (at most :data:`MAX_PIXELS`, checked
from the header and, for PNG and JPEG, from the compressed stream's own header before anything
is decompressed), and that the decoded image has exactly the header's shape. Anything else
raises :class:`FrameCodecError` (a ``ValueError``) naming what was wrong.
"""

from __future__ import annotations

import math
import re
import struct
from typing import Literal

import numpy as np

from .frame import CAMERA_FRAME_VERSION, CameraFrame, CameraFrameHeader
from .geometry import CameraIntrinsics

__all__ = ["MAGIC", "WIRE_VERSION", "MAX_PIXELS", "FrameCodecError", "ImageFormat", "encode_frame", "decode_frame"]

MAGIC = b"ASKC"
#: layout version of this codec (the header's own layout is CAMERA_FRAME_VERSION)
WIRE_VERSION = 1
#: largest image accepted (width x height): 4096 x 4096
MAX_PIXELS = 4096 * 4096

ImageFormat = Literal["raw", "png", "jpeg"]
_FORMATS = ("raw", "png", "jpeg")
_ENCODINGS = ("rgb8", "mono8")
_FIXED = struct.Struct("<4sBBBBHIddHHddddB")
_NAME_RE = re.compile(r"[A-Za-z0-9_]{1,64}")


class FrameCodecError(ValueError):
    """A payload that is not a valid camera frame."""


def encode_frame(frame: CameraFrame, fmt: ImageFormat = "png", quality: int = 90) -> bytes:
    """The payload of ``frame`` with its image as ``fmt`` (``quality`` 1-100 for JPEG)."""
    h = frame.header
    if fmt not in _FORMATS:
        raise ValueError(f"fmt: one of {', '.join(_FORMATS)}, got {fmt!r}")
    if not _NAME_RE.fullmatch(h.camera):
        raise ValueError(f"camera name {h.camera!r}: 1-64 letters, digits or '_'")
    if h.width_px > 0xFFFF or h.height_px > 0xFFFF or h.vehicle > 0xFFFF or h.seq > 0xFFFFFFFF:
        raise ValueError("width, height and vehicle must fit 16 bits and seq 32 bits")
    intr = h.intrinsics
    if fmt == "raw":
        image = np.ascontiguousarray(frame.image).tobytes()
    else:
        import cv2

        img = frame.image if h.encoding == "mono8" else cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)
        params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else []
        ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", img, params)
        if not ok:
            raise ValueError(f"OpenCV could not encode the image as {fmt}")
        image = buf.tobytes()
    name = h.camera.encode("ascii")
    dist = tuple(float(c) for c in intr.dist_coeffs)
    return b"".join((
        _FIXED.pack(MAGIC, WIRE_VERSION, h.version, _FORMATS.index(fmt), _ENCODINGS.index(h.encoding), h.vehicle,
                    h.seq, h.t_capture_s, h.t_available_s, h.width_px, h.height_px, intr.fx_px, intr.fy_px,
                    intr.cx_px, intr.cy_px, len(dist)),
        struct.pack(f"<{len(dist)}d", *dist),
        struct.pack("<B", len(name)), name,
        struct.pack("<I", len(image)), image,
    ))


def _compressed_size(data: bytes, fmt: str) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame, without decompressing."""
    if fmt == "png":
        if len(data) < 24 or data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
            raise FrameCodecError("image: not a PNG stream")
        return struct.unpack(">II", data[16:24])
    i = 2
    if data[:2] != b"\xff\xd8":
        raise FrameCodecError("image: not a JPEG stream")
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise FrameCodecError("image: corrupt JPEG markers")
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        seg = struct.unpack(">H", data[i + 2 : i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[i + 5 : i + 9])
            return width, height
        i += 2 + seg
    raise FrameCodecError("image: JPEG without a frame header")


def decode_frame(payload: bytes, max_pixels: int = MAX_PIXELS) -> CameraFrame:
    """The :class:`CameraFrame` of a payload (:class:`FrameCodecError` if it is not a valid one)."""
    data = bytes(payload)
    if len(data) < _FIXED.size:
        raise FrameCodecError(f"payload: {len(data)} bytes, shorter than the {_FIXED.size}-byte header")
    (magic, wire, version, fmt_i, enc_i, vehicle, seq, t_cap, t_av, width, height, fx, fy, cx, cy,
     n_dist) = _FIXED.unpack_from(data)
    if magic != MAGIC:
        raise FrameCodecError(f"magic: expected {MAGIC!r}, got {magic!r}")
    if wire != WIRE_VERSION:
        raise FrameCodecError(f"wire version {wire}: this codec reads version {WIRE_VERSION}")
    if version != CAMERA_FRAME_VERSION:
        raise FrameCodecError(f"header version {version}: expected {CAMERA_FRAME_VERSION}")
    if fmt_i >= len(_FORMATS) or enc_i >= len(_ENCODINGS):
        raise FrameCodecError(f"image format {fmt_i} / pixel encoding {enc_i}: unknown")
    fmt, encoding = _FORMATS[fmt_i], _ENCODINGS[enc_i]
    if n_dist not in (0, 4, 5, 8):
        raise FrameCodecError(f"dist_coeffs: {n_dist} coefficients (0, 4, 5 or 8)")
    if not (0 < width and 0 < height and width * height <= max_pixels):
        raise FrameCodecError(f"size {width}x{height}: empty or above {max_pixels} pixels")
    off = _FIXED.size
    if len(data) < off + 8 * n_dist + 1:
        raise FrameCodecError("payload: truncated in the distortion coefficients")
    dist = struct.unpack_from(f"<{n_dist}d", data, off)
    off += 8 * n_dist
    n_name = data[off]
    off += 1
    if len(data) < off + n_name + 4:
        raise FrameCodecError("payload: truncated in the camera name")
    try:
        name = data[off : off + n_name].decode("ascii")
    except UnicodeDecodeError:
        raise FrameCodecError("camera name: not ASCII") from None
    if not _NAME_RE.fullmatch(name):
        raise FrameCodecError(f"camera name {name!r}: 1-64 letters, digits or '_'")
    off += n_name
    (n_image,) = struct.unpack_from("<I", data, off)
    off += 4
    if len(data) != off + n_image:
        raise FrameCodecError(f"payload: {len(data)} bytes, the header says {off + n_image}")
    if not all(math.isfinite(v) for v in (t_cap, t_av, fx, fy, cx, cy, *dist)):
        raise FrameCodecError("times, intrinsics and distortion must be finite")
    blob = data[off:]
    channels = 3 if encoding == "rgb8" else 1
    shape = (height, width, 3) if channels == 3 else (height, width)
    if fmt == "raw":
        if n_image != width * height * channels:
            raise FrameCodecError(f"image: {n_image} bytes for a raw {encoding} {width}x{height}")
        image = np.frombuffer(blob, dtype=np.uint8).reshape(shape).copy()
    else:
        if _compressed_size(blob, fmt) != (width, height):
            raise FrameCodecError(f"image: the {fmt} stream's size is not the header's {width}x{height}")
        import cv2

        img = cv2.imdecode(np.frombuffer(blob, dtype=np.uint8),
                           cv2.IMREAD_COLOR if channels == 3 else cv2.IMREAD_GRAYSCALE)
        if img is None or img.shape != shape:
            raise FrameCodecError(f"image: the {fmt} stream does not decode to {shape}")
        image = cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if channels == 3 else img
    try:
        intr = CameraIntrinsics(width, height, fx, fy, cx, cy, tuple(dist))
        header = CameraFrameHeader(name, vehicle, seq, t_cap, t_av, width, height, encoding, intr, version)
        return CameraFrame(header, np.ascontiguousarray(image))
    except ValueError as exc:
        raise FrameCodecError(f"header: {exc}") from None
