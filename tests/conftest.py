import os

# Offscreen rendering (cameras, videos) on the CPU: set before anything imports MuJoCo (sitl does
# the same on import; here it also covers tests that import mujoco first).
os.environ.setdefault("MUJOCO_GL", "osmesa")

import pytest

from companion.cli import single_thread_blas


@pytest.fixture(autouse=True, scope="session")
def _single_thread_blas():
    # Same setting as the CLIs: small matrices are much slower with threaded BLAS.
    with single_thread_blas():
        yield
