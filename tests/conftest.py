import os

import pytest
from hypothesis import settings

from companion.cli import single_thread_blas
from sitl.cameras.rendering import RenderingUnavailable, choose_backend, require_rendering

# Offscreen rendering (the tests marked `rendering`: cameras, videos): a headless OpenGL backend
# chosen before anything imports MuJoCo, osmesa on the CPU or egl. Where none renders those tests
# are skipped with the reason, unless SKELETON_REQUIRE_RENDERING=1 (.ci/run): then they fail.
choose_backend(renders=True)

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


def _need_rendering() -> str:
    try:
        return require_rendering()
    except RenderingUnavailable as exc:
        if os.environ.get("SKELETON_REQUIRE_RENDERING") == "1":
            pytest.fail(f"SKELETON_REQUIRE_RENDERING=1: {exc}")
        pytest.skip(str(exc))


@pytest.fixture(scope="session")
def rendering_backend() -> str:
    """The headless OpenGL backend (for fixtures that render; tests say so with the marker)."""
    return _need_rendering()


@pytest.fixture(autouse=True)
def _rendering(request):
    """A test marked ``rendering`` needs a headless OpenGL backend that renders."""
    if request.node.get_closest_marker("rendering") is not None:
        _need_rendering()


@pytest.fixture
def rig(tmp_path):
    """A vehicle in-process behind loopback sockets, with a fake simulator and a fake GCS
    (:class:`tests.vehicle_rig.Rig`)."""
    from .vehicle_rig import Rig

    r = Rig(tmp_path)
    yield r
    r.close()
