"""Append-only flight logs (companion.logstream): what a killed process leaves is readable."""

import numpy as np
import pytest

from companion.logstream import LogStream, read_log_stream


def test_chunks_read_back_as_the_whole_log(tmp_path):
    rows = {"t": [], "p": []}
    stream = LogStream(tmp_path / "x.stream")
    assert stream.flush(rows) == 0  # nothing yet: no chunk
    for k in range(25):
        rows["t"].append(0.1 * k)
        rows["p"].append(np.full(3, k, dtype=float))
        if k % 7 == 6:
            stream.flush(rows)
    rows["late"] = [np.arange(2)]  # a key that appears later
    stream.flush(rows)
    stream.close()
    got = read_log_stream(tmp_path / "x.stream")
    np.testing.assert_allclose(got["t"], rows["t"])
    np.testing.assert_allclose(got["p"], np.stack(rows["p"]))
    np.testing.assert_array_equal(got["late"], [[0, 1]])
    assert stream.chunks == 4
    with pytest.raises(ValueError, match="closed"):
        stream.flush(rows)


def test_a_truncated_last_chunk_is_left_out(tmp_path, caplog):
    path = tmp_path / "x.stream"
    rows = {"t": [1.0, 2.0]}
    stream = LogStream(path)
    stream.flush(rows)
    rows["t"].append(3.0)
    stream.flush(rows)
    stream.close()
    data = path.read_bytes()
    path.write_bytes(data[:-5])  # killed while writing the second chunk
    got = read_log_stream(path)
    np.testing.assert_allclose(got["t"], [1.0, 2.0])
    assert "unreadable" in caplog.text
    path.write_bytes(b"garbage that is no npy record")
    assert read_log_stream(path) == {}


def test_no_pickles(tmp_path):
    path = tmp_path / "x.stream"
    stream = LogStream(path)
    with pytest.raises(ValueError):
        stream.flush({"obj": [object()]})  # object arrays are refused, never pickled


@pytest.mark.parametrize("keep", [0, 1, 5])
def test_flushing_with_keep_holds_the_lists_short_and_loses_no_row(tmp_path, keep):
    rows = {"t": [], "text": []}
    stream = LogStream(tmp_path / "x.stream")
    for k in range(40):
        rows["t"].append(float(k))
        if k % 9 == 0:
            rows["text"].append(f"event {k}")
        if k % 4 == 3:
            stream.flush(rows, keep=keep)
            assert len(rows["t"]) == min(keep, k + 1)
            assert rows["t"][-1:] == ([float(k)] if keep else [])
    stream.flush(rows, keep=keep)
    stream.close()
    got = read_log_stream(tmp_path / "x.stream")
    np.testing.assert_array_equal(got["t"], np.arange(40.0))
    assert got["text"].tolist() == [f"event {k}" for k in range(0, 40, 9)]
    with pytest.raises(ValueError, match="keep"):
        LogStream(tmp_path / "y.stream").flush(rows, keep=-1)
