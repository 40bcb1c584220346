"""A MAVLink message as the wire delivers it: packed into a MAVLink 2 frame (float32 fields,
truncated trailing zeros) and parsed back by pymavlink, the project's dialect on both sides."""

from companion.mavlink.dialect import load_dialect

D = load_dialect()


def over_mavlink(msg, sysid: int = 1):
    """``msg`` after a MAVLink 2 frame from system ``sysid`` and pymavlink's parser."""
    return frame_and_parsed(msg, sysid)[1]


def frame_and_parsed(msg, sysid: int = 1) -> tuple[bytes, object]:
    """The frame's bytes and the message pymavlink parses from them (sent by system ``sysid``)."""
    data = msg.pack(D.MAVLink(None, srcSystem=sysid, srcComponent=1))
    out = D.MAVLink(None).parse_char(bytearray(data))
    assert out is not None and out.get_srcSystem() == sysid
    return data, out
