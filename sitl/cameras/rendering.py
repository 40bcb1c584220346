"""Headless OpenGL for MuJoCo's offscreen rendering (cameras, videos), chosen only when a run renders.

MuJoCo takes its OpenGL backend from ``MUJOCO_GL`` when it is first imported, and a backend whose
library is missing fails that import. So the choice is made before MuJoCo is imported, by what the
run does (:func:`choose_backend`):

* a run that renders nothing (no ``[[cameras]]``, no video) sets ``MUJOCO_GL=disable``: no OpenGL
  library is loaded at all;
* a run that renders takes ``MUJOCO_GL`` when it is set and its library is present, else the first
  of :data:`BACKENDS` whose library loads: ``osmesa`` (the CPU, Debian's ``libosmesa6``),
  then ``egl`` (libEGL with Mesa's or a GPU's driver). :func:`require_rendering` then renders a
  tiny scene and raises :class:`RenderingUnavailable`, naming the packages to install, when that
  fails (the command lines exit with code 2).

Nothing here imports MuJoCo at module level.
"""

from __future__ import annotations

import ctypes.util
import os
import sys
from functools import lru_cache

__all__ = ["BACKENDS", "RenderingUnavailable", "choose_backend", "require_rendering", "rendering_hint"]

#: headless backends in the order they are tried
BACKENDS = ("osmesa", "egl")
#: the shared library each backend loads (``ctypes.util.find_library`` names, as PyOpenGL looks them up)
_LIBRARIES = {"osmesa": "OSMesa", "egl": "EGL"}
#: ``MUJOCO_GL`` values that turn MuJoCo's rendering off
_DISABLED = ("disable", "disabled", "off", "false", "0")
_INSTALL = ("install Debian's libosmesa6 (CPU rendering: sudo apt-get install libosmesa6) or an EGL driver "
            "(libegl1 and libegl-mesa0, or your GPU's), or set MUJOCO_GL to a backend that works here")


class RenderingUnavailable(RuntimeError):
    """No headless OpenGL backend renders on this machine (the message names what to install)."""


def rendering_hint() -> str:
    """What to install for offscreen rendering."""
    return _INSTALL


def _library_present(backend: str) -> bool:
    """Whether ``backend``'s library loads (found as PyOpenGL finds it, and loadable: a stale entry
    in the linker's cache is not a library); a backend of no known library counts as present."""
    name = _LIBRARIES.get(backend)
    if name is None:
        return True
    path = ctypes.util.find_library(name)
    if path is None:
        return False
    try:
        ctypes.CDLL(path)
    except OSError:
        return False
    return True


def choose_backend(renders: bool, environ=os.environ) -> str:
    """Set ``MUJOCO_GL`` in ``environ`` for a run that ``renders`` or not, before MuJoCo is imported;
    returns the value. Without a backend whose library is present, a rendering run gets
    ``disable`` too (:func:`require_rendering` then says what is missing). Once MuJoCo is imported
    its backend is fixed: the value is left as it is."""
    if "mujoco" in sys.modules:
        return environ.get("MUJOCO_GL", "")
    if not renders:
        environ["MUJOCO_GL"] = "disable"
        return "disable"
    asked = environ.get("MUJOCO_GL", "").strip().lower()
    if asked and asked not in _DISABLED and _library_present(asked):
        return asked
    for backend in BACKENDS:
        if _library_present(backend):
            environ["MUJOCO_GL"] = backend
            return backend
    environ["MUJOCO_GL"] = "disable"
    return "disable"


@lru_cache(maxsize=1)
def _render_check() -> str:
    """``""`` when a tiny scene renders with the backend MuJoCo was imported with, else why not."""
    backend = os.environ.get("MUJOCO_GL", "").strip().lower()
    if backend in _DISABLED:
        missing = [b for b in BACKENDS if not _library_present(b)]
        return (f"no headless OpenGL backend was chosen (MUJOCO_GL={backend}; "
                f"{', '.join(f'{b}: no loadable {_LIBRARIES[b]} library' for b in missing) or 'rendering disabled'})")
    import numpy as np

    try:
        import mujoco
    except Exception as exc:  # (PyOpenGL without its library fails MuJoCo's import: AttributeError)
        return f"MUJOCO_GL={backend}: importing MuJoCo failed: {type(exc).__name__}: {exc}"
    xml = ("<mujoco><visual><global offwidth='16' offheight='16'/></visual><worldbody>"
           "<light pos='0 0 2'/><geom type='sphere' size='0.5' rgba='1 0 0 1'/></worldbody></mujoco>")
    try:
        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        renderer = mujoco.Renderer(model, 16, 16)
        try:
            renderer.update_scene(data)
            image = renderer.render()
        finally:
            renderer.close()
    except Exception as exc:  # (each backend fails its own way: ImportError, RuntimeError, GLError, ...)
        return f"MUJOCO_GL={backend or '(unset: GLFW, which needs a display)'}: {type(exc).__name__}: {exc}"
    if image.shape != (16, 16, 3) or not np.any(image):
        return f"MUJOCO_GL={backend}: the test scene rendered black"
    return ""


def require_rendering() -> str:
    """The backend MuJoCo renders with; :class:`RenderingUnavailable` naming what to install when a
    tiny scene does not render (checked once per process)."""
    reason = _render_check()
    if reason:
        raise RenderingUnavailable(f"offscreen rendering is unavailable: {reason}; {_INSTALL}")
    return os.environ.get("MUJOCO_GL", "")
