"""A tlog left running stays bounded (companion.mavlink.tlog): rotated as logrotate does, every
file whole frames that pymavlink reads, the oldest deleted."""

import pytest
from pymavlink import mavutil

from companion.mavlink.dialect import load_dialect
from companion.mavlink.tlog import TlogWriter, rotated_paths

D = load_dialect()


def _frames(n):
    mav = D.MAVLink(None, srcSystem=7, srcComponent=1)
    # the last payload byte non-zero: MAVLink 2 does not truncate it, every frame has one size
    return [D.MAVLink_system_time_message(k, 0x01000000 + k).pack(mav) for k in range(n)]


def _read(path):
    log = mavutil.mavlink_connection(str(path), dialect="common")
    got = []
    while (m := log.recv_match()) is not None:
        got.append(m.time_unix_usec)
    log.close()
    return got


@pytest.mark.parametrize("keep", [0, 1, 3])
def test_rotated_tlogs_hold_the_newest_frames_within_the_cap(tmp_path, keep):
    frames = _frames(400)
    record = 8 + len(frames[0])
    max_mb = (50 * record + 0.5) / 1e6  # 50 records a file
    tlog = TlogWriter(tmp_path / "link1.tlog", wall_clock=lambda: 1.7e9, max_mb=max_mb, keep=keep)
    for f in frames:
        tlog.write(f)
    tlog.close()
    paths = rotated_paths(tmp_path / "link1.tlog", keep)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)
    assert all(p.stat().st_size <= max_mb * 1e6 for p in paths)
    got = [t for p in reversed(paths) for t in _read(p)]  # oldest file first
    assert got == list(range(400 - len(got), 400)) and len(got) == 50 * (keep + 1)
    assert tlog.rotations == 400 // 50 - 1


def test_without_a_cap_one_file_grows_and_bad_settings_are_refused(tmp_path):
    tlog = TlogWriter(tmp_path / "x.tlog", max_mb=None)
    for f in _frames(100):
        tlog.write(f)
    tlog.close()
    assert [p.name for p in tmp_path.iterdir()] == ["x.tlog"] and len(_read(tmp_path / "x.tlog")) == 100
    with pytest.raises(ValueError, match="max_mb"):
        TlogWriter(tmp_path / "y.tlog", max_mb=0.0)
    with pytest.raises(ValueError, match="keep"):
        TlogWriter(tmp_path / "y.tlog", keep=-1)
