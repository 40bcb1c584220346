import os

# Offscreen rendering (cameras, videos) on the CPU: set before anything imports MuJoCo (sitl does
# the same on import; here it also covers tests that import mujoco first).
os.environ.setdefault("MUJOCO_GL", "osmesa")

import pytest
from hypothesis import settings

from companion.cli import single_thread_blas

# Property tests draw the same examples on every run (each test's own seed, from its name): the
# suite and CI give the same verdict on the same commit. `pytest --hypothesis-profile explore`
# draws fresh examples (and remembers failing ones in .hypothesis/) to look for new counterexamples.
settings.register_profile("default_seeded", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)


def pytest_configure(config):
    if not config.getoption("hypothesis_profile", None):
        settings.load_profile("default_seeded")


@pytest.fixture(autouse=True, scope="session")
def _single_thread_blas():
    # Same setting as the CLIs: small matrices are much slower with threaded BLAS.
    with single_thread_blas():
        yield


@pytest.fixture(autouse=True, scope="session")
def _compiled_kernels():
    """numba's kernels compiled (a clean checkout: 40-70 s on a 2-core VM) or loaded from its cache
    once, before any test: a vehicle or companion process a test starts then loads the cache
    instead of compiling while the test waits for it. (Without numba: nothing to do.)"""
    from sitl.runner import warm_up_kernels

    warm_up_kernels()
    yield
