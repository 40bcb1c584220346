"""Camera frames as bytes and over Zenoh: codec round trip, hostile payloads,
a loopback Zenoh session publishing frames that the companion side decodes and detects."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from companion.vision.frame_codec import (
    MAGIC,
    FrameCodecError,
    decode_frame,
    encode_frame,
)

from ..camera_frames import marker_frame
from ..ports import free_ports
from ..waits import wait_for
from ..zenoh_peers import peer_session

cv2 = pytest.importorskip("cv2")


@pytest.mark.parametrize("fmt", ["raw", "png", "jpeg"])
@pytest.mark.parametrize("encoding", ["rgb8", "mono8"])
def test_codec_round_trip(fmt, encoding):
    f = marker_frame(vehicle=2, seq=41, encoding=encoding)
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
    good = encode_frame(marker_frame(), fmt)
    for payload, reason in _hostile(good):
        with pytest.raises(FrameCodecError, match=reason):
            decode_frame(payload)


def test_compressed_stream_must_match_the_header():
    """A PNG whose own size is not the header's (e.g. a decompression bomb behind a small header)
    is refused before it is decoded; so is garbage in place of the stream."""
    f = marker_frame()
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


@pytest.mark.integration
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

    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    companion = peer_session(listen=(endpoint,), connect=())
    harness = peer_session(listen=(), connect=(endpoint,))
    try:
        sub = CameraSubscriber(companion, "test_cam")
        pubs = [CameraPublisher(harness, "test_cam", v, fmt="png") for v in range(2)]
        assert wait_for(lambda: all(p.matched for p in pubs), 10.0), "the subscription never reached the publishers"
        events = []

        def received(n: int) -> bool:  # each sample awaited before the next: the publishers drop under
            events.extend(sub.drain())  # congestion by design (a newer frame supersedes), a loaded host
            return len(events) >= n     # must not turn that into a lost test sample

        for seq in range(3):
            for v, pub in enumerate(pubs):
                pub.publish(marker_frame(vehicle=v, seq=seq))
                assert wait_for(lambda: received(2 * seq + v + 1), 5.0), events
        block = zenoh.CongestionControl.BLOCK
        harness.put(camera_key("test_cam", 1), encode_frame(marker_frame(vehicle=0), "raw"),
                    congestion_control=block)  # a frame on the wrong key
        assert wait_for(lambda: received(7), 5.0), events
        harness.put(camera_key("test_cam", 0), b"garbage", congestion_control=block)
        assert wait_for(lambda: received(8), 5.0), events
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
