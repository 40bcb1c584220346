import os
from pathlib import Path

import pytest
from hypothesis import settings

from companion.cli import single_thread_blas
from sitl.cameras.rendering import RenderingUnavailable, choose_backend, require_rendering

from .alone import host_turn
from .ports import FleetPorts, fleet_slot, free_ports, worker_index

# Offscreen rendering (the tests marked `rendering`: cameras, videos): a headless OpenGL backend
# chosen before anything imports MuJoCo, osmesa on the CPU or egl. Where none renders those tests
# are skipped with the reason, unless SKELETON_REQUIRE_RENDERING=1 (.ci/run): then they fail.
choose_backend(renders=True)

# Property tests draw the same examples on every run (each test's own seed, from its name): the
# suite and CI give the same verdict on the same commit. `pytest --hypothesis-profile explore`
# draws fresh examples (and remembers failing ones in .hypothesis/) to look for new counterexamples.
settings.register_profile("default_seeded", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)

#: every test is in one tier (its marker: `pytest -m unit`): the folder it lives in (tests/<tier>/),
#: unless the test itself is marked with another (a flight among a module's unit tests)
TIERS = ("unit", "integration", "e2e")
TESTS = Path(__file__).resolve().parent


def pytest_configure(config):
    if not config.getoption("hypothesis_profile", None):
        settings.load_profile("default_seeded")
    _compile_packages()
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput"):
        _warm_kernels_for_the_workers()


def _warm_kernels_for_the_workers() -> None:
    """Under ``pytest -n N`` the controller compiles numba's kernels (or loads them) once, before
    its workers start: each worker then loads the cache instead of compiling the same kernels at
    the same time as the others (on a clean checkout, a minute of CPU per worker)."""
    from sitl.runner import warm_up_kernels

    warm_up_kernels()


def _compile_packages() -> None:
    """The project's modules compiled to bytecode once, before the suite starts its hundreds of
    processes (vehicles, companions, command lines, Dask workers): each would otherwise compile
    what it imports from source when ``PYTHONDONTWRITEBYTECODE`` is set (CI images set it), and
    without it they would race to write the same files. Up-to-date files are skipped."""
    import compileall

    for package in ("companion", "link_firmware_sim", "sitl"):
        compileall.compile_dir(str(TESTS.parent / package), quiet=2, workers=1)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Each test gets its tier's marker (before ``-m`` selects): its own, else its folder's."""
    for item in items:
        try:
            folder = Path(item.path).resolve().relative_to(TESTS).parts[0]
        except ValueError:
            continue  # a test file outside tests/ (pytest given another path)
        if folder not in TIERS:
            raise pytest.UsageError(f"{item.nodeid}: a test lives in tests/unit, tests/integration or tests/e2e")
        own = {m.name for m in item.iter_markers() if m.name in TIERS}
        if len(own) > 1:
            raise pytest.UsageError(f"{item.nodeid}: in one tier, not {sorted(own)}")
        if not own:
            item.add_marker(folder)


@pytest.fixture(autouse=True, scope="session")
def _single_thread_blas():
    # Same setting as the CLIs: small matrices are much slower with threaded BLAS.
    with single_thread_blas():
        yield


@pytest.fixture(scope="session")
def compiled_kernels() -> None:
    """numba's kernels compiled (a clean checkout: about a minute on 2 cores) or loaded from its
    cache once, for the tests that start vehicle, companion or fleet processes or wait on real
    time: a process a test starts then loads the cache instead of compiling while the test waits
    for it. Tests that call a kernel in this process load it when they first call it. (Without
    numba: nothing to do.)"""
    from sitl.runner import warm_up_kernels

    warm_up_kernels()


@pytest.fixture(autouse=True)
def _fleets_alone(request, tmp_path_factory):
    """Under pytest-xdist a fleet test (one that takes ``fleet_ports``) runs with no other test beside
    it, the others side by side (:mod:`tests.alone`)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    with host_turn(tmp_path_factory.getbasetemp().parent, "fleet_ports" in request.fixturenames):
        yield


@pytest.fixture
def fleet_ports(compiled_kernels) -> FleetPorts:
    """Ports of this test's own for a fleet (an instance offset no other test on this host holds
    meanwhile, see :func:`tests.ports.fleet_slot`) and a free GCS port: tests run side by side
    under pytest-xdist (``-n 2``) without a port clash."""
    (gcs_port,) = free_ports(1, udp=True)
    with fleet_slot(preferred=worker_index()) as k:
        yield FleetPorts(k, gcs_port)


def _need(check, unavailable: type[Exception], env: str):
    """``check()``'s value; when it raises ``unavailable``: a skip with its reason, or a failure
    where ``env`` is set to 1 (CI, which installs what the check needs)."""
    try:
        return check()
    except unavailable as exc:
        if os.environ.get(env) == "1":
            pytest.fail(f"{env}=1: {exc}")
        pytest.skip(str(exc))


def _need_rendering() -> str:
    return _need(require_rendering, RenderingUnavailable, "SKELETON_REQUIRE_RENDERING")


@pytest.fixture(scope="session")
def browser_binary() -> str:
    """Debian's Chromium, for the tests marked ``browser`` (skipped without it, failed with
    ``SKELETON_REQUIRE_BROWSER=1``)."""
    from sitl.view.browser import BrowserUnavailable, require_browser

    return _need(require_browser, BrowserUnavailable, "SKELETON_REQUIRE_BROWSER")


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
def rig(tmp_path, compiled_kernels):
    """A vehicle in-process behind loopback sockets, with a fake simulator and a fake GCS
    (:class:`tests.vehicle_rig.Rig`)."""
    from .vehicle_rig import Rig

    r = Rig(tmp_path)
    yield r
    r.close()


@pytest.fixture
def dask_cluster(tmp_path):
    """A Dask scheduler and two workers started as a user starts them (dask scheduler, dask worker)
    on loopback; yields the scheduler's address."""
    import json
    import signal
    import subprocess
    import sys

    from .paths import ROOT
    from .waits import wait_for

    dask = str(Path(sys.executable).parent / "dask")
    scheduler_file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(scheduler_file)], cwd=ROOT, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        assert wait_for(scheduler_file.exists, 60.0), "the scheduler wrote no address"
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1",
                                           "--no-dashboard", "--host", "127.0.0.1"], cwd=ROOT,
                                          start_new_session=True, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
        address = json.loads(scheduler_file.read_text())["address"]
        from distributed import Client

        with Client(address, timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in procs:
            os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
