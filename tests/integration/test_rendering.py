"""MuJoCo's OpenGL backend is chosen by what a run renders (sitl/cameras/rendering.py): a run without cameras
or video loads no OpenGL library; one that renders without a headless backend exits 2 naming what
to install."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sitl.cameras.rendering import choose_backend

from ..paths import ROOT

THREE_LINK = ROOT / "configs" / "sitl" / "chain" / "three_link.toml"
CAMERA = ROOT / "configs" / "sitl" / "cameras" / "three_link_camera.toml"


def _python(code: str, **env) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    environ.update(env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=environ,
                          timeout=300)


def test_a_run_that_renders_nothing_disables_opengl(monkeypatch):
    monkeypatch.delitem(sys.modules, "mujoco", raising=False)  # (as before MuJoCo's import)
    env: dict = {"MUJOCO_GL": "osmesa"}  # (a stale setting is overridden: the run renders nothing)
    assert choose_backend(False, env) == "disable" and env["MUJOCO_GL"] == "disable"


@pytest.mark.parametrize("asked", ["", "osmesa", "egl", "disable"])
def test_a_run_that_renders_takes_a_backend_whose_library_is_present(monkeypatch, asked):
    import sitl.cameras.rendering as rendering

    monkeypatch.delitem(sys.modules, "mujoco", raising=False)  # (as before MuJoCo's import)
    for present in ({"osmesa", "egl"}, {"egl"}, set()):
        monkeypatch.setattr(rendering, "_library_present", lambda b, present=present: b in present)
        env = {"MUJOCO_GL": asked} if asked else {}
        got = choose_backend(True, env)
        if asked in present:
            want = asked  # the user's choice, where its library is there
        else:
            want = next((b for b in rendering.BACKENDS if b in present), "disable")
        assert got == want and env["MUJOCO_GL"] == want


def test_the_batch_flight_loads_no_opengl_library():
    """The flight's modules imported as ``sitl fly`` imports them for a scenario without cameras:
    neither PyOpenGL nor any GL library is in the process."""
    r = _python(
        "import sys\n"
        "from sitl.__main__ import _prepare_rendering\n"
        "from sitl.scenario import load_scenario\n"
        f"assert _prepare_rendering(load_scenario({str(THREE_LINK)!r}), None) is None\n"
        "import sitl.scenarios.chain.flight, sitl.fleet.launcher, mujoco\n"
        "maps = open('/proc/self/maps').read()\n"
        "gl = sorted({l.split('/')[-1] for l in maps.splitlines() if any(k in l for k in ('libOSMesa', 'libEGL', 'libGL'))})\n"
        "print('OpenGL' in sys.modules, gl)\n")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False []"


def test_a_camera_scenario_without_a_backend_exits_2_naming_the_package(tmp_path):
    """The command line on a machine where no backend's library is found (the lookup answers no)."""
    r = _python(
        "import sys\n"
        "import sitl.cameras.rendering\n"
        "sitl.cameras.rendering._library_present = lambda backend: False\n"
        "from sitl.__main__ import main\n"
        f"sys.exit(main(['fly', '--config', {str(CAMERA)!r}, '--duration', '8', '--out', {str(tmp_path)!r}, '--quiet']))\n")
    assert r.returncode == 2, r.stderr
    assert "libosmesa6" in r.stderr and "cameras" in r.stderr and "Traceback" not in r.stderr
    assert not any(tmp_path.iterdir())  # refused before the flight


def test_a_video_without_a_backend_exits_2_naming_the_package(tmp_path):
    r = _python(
        "import sys\n"
        "import sitl.cameras.rendering\n"
        "sitl.cameras.rendering._library_present = lambda backend: False\n"
        "from sitl.__main__ import main\n"
        f"sys.exit(main(['fly', '--config', {str(THREE_LINK)!r}, '--video', {str(tmp_path / 'x.mp4')!r}, "
        f"'--out', {str(tmp_path / 'run')!r}, '--quiet']))\n")
    assert r.returncode == 2, r.stderr
    assert "--video" in r.stderr and "libosmesa6" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.rendering
def test_the_chosen_backend_renders():
    from sitl.cameras.rendering import require_rendering

    assert require_rendering() in ("osmesa", "egl", "glfw")
