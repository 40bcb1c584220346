"""Camera frames as bytes and over Zenoh: codec round trip, hostile payloads,
a loopback Zenoh session publishing frames that the companion side decodes and detects."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest

from companion.vision.frame import CameraFrame, CameraFrameHeader
from companion.vision.frame_codec import (
    MAGIC,
    FrameCodecError,
    decode_frame,
    encode_frame,
)
from companion.vision.geometry import CameraIntrinsics

cv2 = pytest.importorskip("cv2")


def _marker_frame(vehicle: int = 0, seq: int = 0, encoding: str = "rgb8", side_px: int = 96) -> CameraFrame:
    """A 320x240 frame with ArUco marker 7 (DICT_4X4_50) pasted fronto-parallel at the centre."""
    from companion.vision.markers import marker_image

    img, _ = marker_image("DICT_4X4_50", 7, bit_px=16)
    img = cv2.resize(img, (side_px, side_px), interpolation=cv2.INTER_AREA)
    canvas = np.full((240, 320), 128, np.uint8)
    y0, x0 = 120 - side_px // 2, 160 - side_px // 2
    canvas[y0 : y0 + side_px, x0 : x0 + side_px] = img
    image = canvas if encoding == "mono8" else np.repeat(canvas[:, :, None], 3, axis=2)
    intr = CameraIntrinsics.from_fov(320, 240, 60.0, (0.01, -0.002, 0.0, 0.0))
    h = CameraFrameHeader(f"cam{vehicle + 1}", vehicle, seq, 1.25 + seq, 1.30 + seq, 320, 240, encoding, intr)
    return CameraFrame(h, image)


@pytest.mark.parametrize("fmt", ["raw", "png", "jpeg"])
@pytest.mark.parametrize("encoding", ["rgb8", "mono8"])
def test_codec_round_trip(fmt, encoding):
    f = _marker_frame(vehicle=2, seq=41, encoding=encoding)
    back = decode_frame(encode_frame(f, fmt, quality=95))
    assert back.header == f.header
    if fmt == "jpeg":
        assert np.abs(back.image.astype(int) - f.image).mean() < 2.0
    else:
        assert np.array_equal(back.image, f.image)


def _hostile(good: bytes) -> list[tuple[bytes, str]]:
    n = len(good)
    bad_magic = b"XXXX" + good[4:]
    wire = good[:4] + bytes([99]) + good[5:]
    header_v = good[:5] + bytes([99]) + good[6:]
    fmt = good[:6] + bytes([7]) + good[7:]
    huge = bytearray(good)
    struct.pack_into("<HH", huge, 4 + 4 + 2 + 4 + 16, 60000, 60000)  # width, height
    nan_t = bytearray(good)
    struct.pack_into("<d", nan_t, 4 + 4 + 2 + 4, float("nan"))
    return [(b"", "shorter"), (good[:20], "shorter"), (good[:-1], "header says"), (good + b"\0", "header says"),
            (bad_magic, "magic"), (wire, "wire version"), (header_v, "header version"), (fmt, "unknown"),
            (bytes(huge), "size"), (bytes(nan_t), "finite"), (b"\0" * n, "magic")]


@pytest.mark.parametrize("fmt", ["raw", "png"])
def test_hostile_payloads_are_rejected(fmt):
    good = encode_frame(_marker_frame(), fmt)
    for payload, reason in _hostile(good):
        with pytest.raises(FrameCodecError, match=reason):
            decode_frame(payload)


def test_compressed_stream_must_match_the_header():
    """A PNG whose own size is not the header's (e.g. a decompression bomb behind a small header)
    is refused before it is decoded; so is garbage in place of the stream."""
    f = _marker_frame()
    good = encode_frame(f, "png")
    big = cv2.imencode(".png", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    head = good[: len(good) - len(good.split(b"\x89PNG", 1)[1]) - 4 - 4]  # up to the image length field
    swapped = head + struct.pack("<I", len(big)) + big
    with pytest.raises(FrameCodecError, match="size is not the header"):
        decode_frame(swapped)
    junk = head + struct.pack("<I", 30) + b"\x89PNG\r\n\x1a\n" + b"\0" * 22
    with pytest.raises(FrameCodecError):
        decode_frame(junk)
    assert MAGIC == good[:4]


def test_frames_over_zenoh_loopback_are_decoded_and_detected():
    """Harness side publishes vehicles' frames on <prefix>/camera/<v>/image; the companion side's
    subscriber decodes them and its marker pipeline detects the marker (the path a real camera
    on the onboard computer feeds). A frame on another vehicle's key and garbage are errors."""
    zenoh = pytest.importorskip("zenoh")
    from companion.vision.camera_wire import (
        CameraPublisher,
        CameraSubscriber,
        camera_key,
    )
    from companion.vision.pnp import MarkerPipeline, PipelineConfig

    def session(listen=None, connect=None):
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", f'["{listen}"]' if listen else "[]")
        c.insert_json5("connect/endpoints", f'["{connect}"]' if connect else "[]")
        return zenoh.open(c)

    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    companion = session(listen=endpoint)
    harness = session(connect=endpoint)
    try:
        sub = CameraSubscriber(companion, "test_cam")
        pubs = [CameraPublisher(harness, "test_cam", v, fmt="png") for v in range(2)]
        time.sleep(0.5)  # the sessions connect and the subscription propagates
        for seq in range(3):
            for v, pub in enumerate(pubs):
                pub.publish(_marker_frame(vehicle=v, seq=seq))
        harness.put(camera_key("test_cam", 1), encode_frame(_marker_frame(vehicle=0), "raw"))  # wrong key
        harness.put(camera_key("test_cam", 0), b"garbage")
        events = []
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and len(events) < 8:
            events += sub.drain()
            time.sleep(0.02)
        frames = [e[1] for e in events if e[0] == "frame"]
        errors = [e for e in events if e[0] == "error"]
        assert len(frames) == 6 and len(errors) == 2, events
        assert sorted((f.header.vehicle, f.header.seq) for f in frames) == [(v, s) for v in range(2) for s in range(3)]
        pipe = MarkerPipeline(PipelineConfig(marker_length_m=0.2))
        for f in frames:
            dets, poses = pipe.measure(f.image, f.header.intrinsics)
            assert [d.marker_id for d in dets] == [7] and len(poses) == 1
        for p in pubs:
            p.close()
        sub.close()
    finally:
        harness.close()
        companion.close()
