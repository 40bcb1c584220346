"""Reading a log stream as it grows (companion.logstream.LogStreamReader, read_log_stream): new
rows only, a chunk still being written is neither returned nor skipped."""

import logging

import numpy as np
import pytest

from companion.logstream import LogStream, LogStreamReader, read_log_stream


def add(rows, k0, k1):
    for k in range(k0, k1):
        rows.setdefault("t", []).append(0.01 * k)
        rows.setdefault("p", []).append(np.array([k, -k, 2 * k], dtype=float))
        rows.setdefault("flags", []).append(np.uint8(k % 16))


def check_rows(got, k0, k1):
    assert set(got) == {"t", "p", "flags"}
    np.testing.assert_allclose(got["t"], 0.01 * np.arange(k0, k1))
    np.testing.assert_array_equal(got["p"][:, 0], np.arange(k0, k1))
    assert got["p"].shape == (k1 - k0, 3)
    assert got["flags"].dtype == np.uint8


def test_read_new_returns_only_the_new_rows(tmp_path):
    path = tmp_path / "x.stream"
    reader = LogStreamReader(path)
    assert reader.read_new() == {}  # no file yet
    stream = LogStream(path)
    assert reader.read_new() == {}  # an empty file
    rows: dict[str, list] = {}
    bounds = [0, 5, 6, 17, 40]
    for k0, k1 in zip(bounds, bounds[1:]):
        add(rows, k0, k1)
        stream.flush(rows)
        check_rows(reader.read_new(), k0, k1)
        assert reader.read_new() == {}  # nothing new
    add(rows, 40, 43)
    stream.flush(rows)
    add(rows, 43, 50)
    stream.flush(rows)
    check_rows(reader.read_new(), 40, 50)  # two chunks at once, concatenated
    stream.close()
    check_rows(LogStreamReader(path).read_new(), 0, 50)  # a new reader reads from the start


def test_a_key_appearing_later_comes_with_its_chunk(tmp_path):
    path = tmp_path / "x.stream"
    stream = LogStream(path)
    reader = LogStreamReader(path)
    rows = {"t": [0.0, 0.1]}
    stream.flush(rows)
    assert set(reader.read_new()) == {"t"}
    rows["t"].append(0.2)
    rows["late"] = [np.arange(3)]
    stream.flush(rows)
    got = reader.read_new()
    np.testing.assert_allclose(got["t"], [0.2])
    np.testing.assert_array_equal(got["late"], [[0, 1, 2]])
    stream.close()


def _chunks(tmp_path):
    """The bytes of a stream's two chunks (rows 0..7 and 8..19)."""
    path = tmp_path / "source.stream"
    stream = LogStream(path)
    rows: dict[str, list] = {}
    add(rows, 0, 8)
    stream.flush(rows)
    first = path.stat().st_size
    add(rows, 8, 20)
    stream.flush(rows)
    stream.close()
    data = path.read_bytes()
    return data[:first], data[first:]


def _header_size(chunk: bytes) -> int:
    """Bytes of a chunk's first record (its keys), read back with numpy."""
    import io

    f = io.BytesIO(chunk)
    np.load(f, allow_pickle=False)
    return f.tell()


@pytest.mark.parametrize("where", ["1 byte", "half the magic", "in the header", "after the header",
                                   "half", "all but 1 byte"])
def test_a_partly_written_chunk_is_neither_returned_nor_skipped(tmp_path, where, caplog):
    first, second = _chunks(tmp_path)
    cut = {"1 byte": 1, "half the magic": 3, "in the header": _header_size(second) // 2,
           "after the header": _header_size(second), "half": len(second) // 2,
           "all but 1 byte": len(second) - 1}[where]
    assert 0 < cut < len(second)
    path = tmp_path / "x.stream"
    path.write_bytes(first)
    reader = LogStreamReader(path)
    check_rows(reader.read_new(), 0, 8)
    with open(path, "ab") as f:
        f.write(second[:cut])  # the writer is in the middle of the chunk
    with caplog.at_level(logging.WARNING, logger="companion.logstream"):
        assert reader.read_new() == {}
        assert reader.read_new() == {}  # read again each time, never skipped
    assert caplog.records == []  # not final: nothing to report
    with open(path, "ab") as f:
        f.write(second[cut:])
    check_rows(reader.read_new(), 8, 20)
    assert reader.read_new() == {}


def test_read_log_stream_of_a_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_log_stream(tmp_path / "nothing.stream")


@pytest.mark.parametrize("keep", [1, 0.5, -1])
def test_read_log_stream_of_a_truncated_file(tmp_path, keep, caplog):
    first, second = _chunks(tmp_path)
    path = tmp_path / "x.stream"
    cut = keep if keep >= 1 else (int(keep * len(second)) if keep > 0 else len(second) + keep)
    path.write_bytes(first + second[:cut])
    with caplog.at_level(logging.WARNING, logger="companion.logstream"):
        got = read_log_stream(path)
    check_rows(got, 0, 8)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and r.name == "companion.logstream"]
    assert len(warnings) == 1
    assert f"byte {len(first)}" in warnings[0].getMessage()
    assert f"{cut} byte(s)" in warnings[0].getMessage()


def test_read_log_stream_of_a_whole_file_logs_nothing(tmp_path, caplog):
    first, second = _chunks(tmp_path)
    path = tmp_path / "x.stream"
    path.write_bytes(first + second)
    with caplog.at_level(logging.WARNING, logger="companion.logstream"):
        check_rows(read_log_stream(path), 0, 20)
    assert caplog.records == []


def test_a_chunk_whose_header_is_no_list_of_keys_is_not_read(tmp_path, caplog):
    first, _ = _chunks(tmp_path)
    path = tmp_path / "x.stream"
    with open(path, "wb") as f:
        f.write(first)
        np.save(f, np.arange(3.0))  # a record where a header belongs
        np.save(f, np.arange(3.0))
    with caplog.at_level(logging.WARNING, logger="companion.logstream"):
        check_rows(read_log_stream(path), 0, 8)
    assert "not a list of keys" in caplog.text
