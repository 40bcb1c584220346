import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from companion.__main__ import main as companion_main
from companion.estimation.constraints import constraint_residual
from companion.estimation.semi import parse_groups, semi_distributed_apply
from companion.replay import REPLAY_KEYS
from sitl.bench.ekf_chain import ChainRun, simulate_ekf_chain
from sitl.synthetic import ChainMotion


@pytest.fixture(scope="module")
def stream_arrays():
    run = ChainRun(motion=replace(ChainMotion(), n_links=5), duration_s=1.0)
    return simulate_ekf_chain(run, seed=3).replay_arrays()


def _write(path, arrays):
    np.savez(path, **arrays)
    return str(path)


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "companion", "replay", *args, "--quiet"], capture_output=True, text=True, timeout=120
    )


def test_replay_cli_roundtrip(tmp_path, stream_arrays):
    src = _write(tmp_path / "in.npz", stream_arrays)
    dst = tmp_path / "out.npz"
    proc = _cli(src, str(dst), "--groups", "1,2/3,4,5", "--eps", "0.005")
    assert proc.returncode == 0, proc.stderr
    assert "constraint error" in proc.stdout
    out = np.load(dst)
    K, n = stream_arrays["p"].shape[:2]
    for key in REPLAY_KEYS:
        assert out[key].shape == stream_arrays[key].shape
    for key in ("t", "w", "d"):
        np.testing.assert_array_equal(out[key], stream_arrays[key])
    assert out["residual_before"].shape == out["residual_after"].shape == out["iterations"].shape == (K,)
    assert out["shifts"].shape == (K, 2, 6)
    assert str(out["groups"]) == "1,2/3,4,5"
    groups = parse_groups("1,2/3,4,5", n)
    for k in (0, K // 2, K - 1):
        args = [stream_arrays[key][k] for key in ("p", "v", "q", "w")]
        ref = semi_distributed_apply(*args, stream_arrays["d"], stream_arrays["P"][k], groups,
                                     __import__("companion.estimation.sckf", fromlist=["CAParams"]).CAParams(eps=0.005))
        np.testing.assert_allclose(out["p"][k], ref.p, atol=1e-12)
        np.testing.assert_allclose(out["q"][k], ref.q, atol=1e-12)
        np.testing.assert_allclose(out["P"][k], ref.P, atol=1e-12)
        before = np.linalg.norm(constraint_residual(*args, stream_arrays["d"]))
        assert out["residual_before"][k] == pytest.approx(before)
    assert np.all(out["residual_after"] < out["residual_before"])
    # Running the output back through replay changes nothing: it already satisfies the constraints.
    again = tmp_path / "again.npz"
    proc = _cli(str(dst), str(again), "--groups", "1,2,3,4,5", "--eps", "0.1")
    assert proc.returncode == 0, proc.stderr
    np.testing.assert_array_equal(np.load(again)["iterations"], 0)


def test_replay_default_is_one_group(tmp_path, stream_arrays):
    src = _write(tmp_path / "in.npz", stream_arrays)
    dst = tmp_path / "out.npz"
    assert companion_main(["replay", src, str(dst), "--quiet"]) == 0
    out = np.load(dst)
    assert str(out["groups"]) == "1,2,3,4,5"
    assert out["residual_after"].max() <= 0.01


def _broken(stream_arrays, **changes):
    arrays = {k: v.copy() for k, v in stream_arrays.items()}
    for key, fn in changes.items():
        arrays[key] = fn(arrays[key])
    return arrays


def _set(index, value):
    def fn(a):
        a[index] = value
        return a

    return fn


def _non_pd(a):
    a[4, 2] = -np.eye(9)
    return a


def _asymmetric(a):
    a[1, 0, 0, 1] += 5.0
    return a


BAD_INPUTS = {
    "missing key": (lambda s: {k: v for k, v in s.items() if k != "P"}, ["missing key", "'P'"]),
    "wrong shape": (lambda s: _broken(s, q=lambda a: a[..., :3]), ["'q'", "shape"]),
    "nan position": (lambda s: _broken(s, p=_set((7, 3, 1), np.nan)), ["p[7, 3, 1]", "step 7, link 4", "not finite"]),
    "non-PD covariance": (lambda s: _broken(s, P=_non_pd), ["P[4, 2]", "step 4, link 3", "positive definite"]),
    "asymmetric covariance": (lambda s: _broken(s, P=_asymmetric), ["P[1, 0]", "symmetric"]),
    "non-unit quaternion": (lambda s: _broken(s, q=_set((2, 1), [2.0, 0, 0, 0])), ["q[2, 1]", "norm"]),
    "time goes back": (lambda s: _broken(s, t=_set(5, -1.0)), ["t[5]", "back in time"]),
    "text array": (lambda s: {**s, "d": np.array([["a", "b", "c"]] * 5)}, ["'d'", "dtype"]),
}


@pytest.mark.parametrize("case", BAD_INPUTS.values(), ids=BAD_INPUTS.keys())
def test_replay_rejects_bad_input(tmp_path, stream_arrays, case):
    make, fragments = case
    src = _write(tmp_path / "bad.npz", make(stream_arrays))
    dst = tmp_path / "out.npz"
    proc = _cli(src, str(dst))
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    for fragment in fragments:
        assert fragment in proc.stderr, proc.stderr
    assert not dst.exists()


@pytest.mark.parametrize(
    "extra, fragment",
    [
        (["--groups", "1,2/4,5"], "group 2"),
        (["--groups", "1,2/3,x"], "cannot read group 2"),
        (["--eps", "-1"], "eps"),
        (["--alpha", "0"], "alpha"),
    ],
)
def test_replay_rejects_bad_options(tmp_path, stream_arrays, extra, fragment):
    src = _write(tmp_path / "in.npz", stream_arrays)
    proc = _cli(src, str(tmp_path / "out.npz"), *extra)
    assert proc.returncode == 2 and fragment in proc.stderr and "Traceback" not in proc.stderr


def test_replay_rejects_missing_and_garbage_files(tmp_path):
    proc = _cli(str(tmp_path / "nope.npz"), str(tmp_path / "out.npz"))
    assert proc.returncode == 2 and "no such file" in proc.stderr
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"\x00\x01 not a zip")
    proc = _cli(str(garbage), str(tmp_path / "out.npz"))
    assert proc.returncode == 2 and "not a readable .npz" in proc.stderr and "Traceback" not in proc.stderr


def test_cli_help_and_no_command():
    proc = subprocess.run([sys.executable, "-m", "companion", "replay", "--help"], capture_output=True, text=True)
    assert proc.returncode == 0 and "--groups" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "companion"], capture_output=True, text=True)
    assert proc.returncode == 2 and "replay" in proc.stderr
