"""Cameras and ArUco markers in the MuJoCo SITL (the slung-load report's sec. III).

Config (a scenario's ``[[cameras]]`` and ``[[markers]]`` arrays of tables):

* :class:`CameraMount` -- a camera fixed to a body (``"world"`` or any body of the model, e.g.
  ``"link2"``): pose in the body (position, optical axis, image right), resolution, intrinsics
  from the vertical field of view (:meth:`~companion.vision.geometry.CameraIntrinsics.from_fov`),
  optional distortion, rate, latency, seeded pixel noise and optional motion blur.
* :class:`MarkerMount` -- an ArUco marker (dictionary, id, side of the black square) on the face
  of a body: a thin box whose top face carries the marker, generated with ``cv2.aruco``, and a
  site ``marker<id>`` at the marker's centre with the marker's axes (the ground truth).

:func:`vision_mjcf` adds both to the generated MJCF (cameras, marker boxes, textures as in-memory
PNG assets, the offscreen buffer). :class:`CameraRig` renders every camera offscreen on the CPU
with ``mujoco.Renderer`` at its rate, on the simulation clock: a frame is captured at the physics
tick of its period (averaged over ``blur_samples`` renders across ``exposure_s`` for motion
blur; stamped mid-exposure), seen through the camera's true lens (its distortion and, with a
calibration error, its true intrinsics: :meth:`~sitl.cameras.config.CameraMount.true_intrinsics`;
the frame carries the nominal ones), given Gaussian pixel noise from its own seeded stream, lost
with the camera's ``drop_probability``, and delivered ``latency_s`` plus its seeded jitter later, in
capture order per camera (:meth:`CameraRig.poll`). The camera's sensor response
(:class:`~sitl.cameras.photometry.SensorResponse`) puts vignetting and a gain drift before the
noise and a tone curve after it. With a ``[scene]`` (:mod:`sitl.cameras.scene`), :func:`vision_mjcf`
adds the ground, the light and the clutter (:mod:`sitl.cameras.backdrop`), and the rig dims the sun
by its clouds at every render and renders shadows if asked. Each frame keeps the ground truth at
capture (camera and marker poses in the world) beside the companion's
:class:`~companion.vision.frame.CameraFrame`.

Rendering needs an OpenGL context without a display, chosen before MuJoCo is imported
(:mod:`sitl.cameras.rendering`: osmesa on the CPU, or egl); a rig or a video on a machine where nothing
renders raises :class:`~sitl.cameras.rendering.RenderingUnavailable`, which names what to install.
Renderers hold GL contexts: :meth:`CameraRig.close` (or ``with``) frees them.
"""

from __future__ import annotations

import logging
import re
import time
from collections import deque
from dataclasses import dataclass, replace

import cv2
import mujoco
import numpy as np

from companion.estimation.so3 import rotmat_to_quat
from companion.vision.frame import CameraFrame, CameraFrameHeader
from companion.vision.geometry import CV_TO_MUJOCO_CAM, CameraIntrinsics
from companion.vision.markers import marker_image

from .backdrop import scene_mjcf
from .config import CameraMount, MarkerMount
from .photometry import SensorResponse, SunSchedule
from .rendering import require_rendering
from .scene import SceneConfig, scene_rng

__all__ = ["CameraMount", "MarkerMount", "FrameTruth", "CapturedFrame", "mount_rng", "vision_mjcf", "CameraRig",
           "Delivery", "pixel_maps", "fast_renderer"]

log = logging.getLogger(__name__)

#: thickness of the box that carries a marker [m]
MARKER_THICKNESS_M = 0.001
#: a marker's own light (material emission) under MuJoCo's default lighting; with a lit
#: ``[scene]`` markers are matte paper (0)
MARKER_EMISSION = 0.3


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def _insert_in_body(xml: str, body: str, text: str) -> str:
    """``text`` inserted as the first children of ``body`` (``"world"``: the worldbody)."""
    if body == "world":
        pattern = r"<worldbody>"
    else:
        pattern = rf'<body name="{re.escape(body)}"[^>]*>'
    m = re.search(pattern, xml)
    if m is None:
        names = ["world"] + re.findall(r'<body name="([^"]+)"', xml)
        raise ValueError(f"body: no body {body!r} in the model (bodies: {', '.join(names)})")
    return xml[: m.end()] + "\n" + text + xml[m.end():]


def _ensure_offscreen(xml: str, width: int, height: int) -> str:
    m = re.search(r'<global offwidth="(\d+)" offheight="(\d+)"/>', xml)
    if m is None:
        return xml.replace("<worldbody>", f'<visual><global offwidth="{width}" offheight="{height}"/></visual>\n'
                                          "<worldbody>", 1)
    w, h = max(int(m.group(1)), width), max(int(m.group(2)), height)
    return xml[: m.start()] + f'<global offwidth="{w}" offheight="{h}"/>' + xml[m.end():]


def mount_rng(seed: int, kind: str, key: int) -> np.random.Generator:
    """The stream that places camera ``key`` (its index) or marker ``key`` (its id) of a
    scenario of ``seed`` (:meth:`~.config.CameraMount.true_mount`)."""
    return np.random.default_rng([seed, 0x3E77 if kind == "camera" else 0x3A7C, key])


def vision_mjcf(xml: str, cameras: tuple[CameraMount, ...], markers: tuple[MarkerMount, ...],
                min_offscreen: tuple[int, int] = (640, 480), scene: SceneConfig | None = None,
                seed: int = 0) -> tuple[str, dict[str, bytes]]:
    """``xml`` with the cameras (``cam_<name>``), the marker boxes (``marker<id>``, textured) and
    their sites (``marker<id>``), each where its mount error (from ``seed``: :func:`mount_rng`)
    really puts it, an offscreen buffer large enough for every camera and, unless it is the
    default one, ``scene`` (its random parts from ``seed``: :func:`~sitl.cameras.backdrop.scene_mjcf`);
    returns the MJCF and the PNG assets it names (pass both to ``MjModel.from_xml_string``)."""
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"cameras: names must be unique, got {names}")
    ids = [m.id for m in markers]
    if len(set(ids)) != len(ids):
        raise ValueError(f"markers: ids must be unique, got {ids}")
    assets: dict[str, bytes] = {}
    asset_lines = []
    emission = 0.0 if scene is not None and scene.lighting.enabled else MARKER_EMISSION
    for m in markers:
        img, fraction = marker_image(m.dictionary, m.id, bit_px=32, quiet_zone_bits=m.quiet_zone_bits)
        ok, png = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        assert ok
        assets[f"marker{m.id}.png"] = png.tobytes()
        asset_lines += [
            f'    <texture name="marker{m.id}_tex" type="2d" file="marker{m.id}.png"/>',
            f'    <material name="marker{m.id}_mat" texture="marker{m.id}_tex" texrepeat="1 1" texuniform="false" '
            f'specular="0" shininess="0" reflectance="0" emission="{emission:.9g}"/>',
        ]
        half = 0.5 * m.size_m / fraction
        pos, R = m.true_mount(mount_rng(seed, "marker", m.id))
        q = rotmat_to_quat(R)
        centre = pos - R[:, 2] * (0.5 * MARKER_THICKNESS_M)  # the face at pos
        xml = _insert_in_body(xml, m.body, (
            f'<geom name="marker{m.id}" type="box" size="{half:.9g} {half:.9g} {0.5 * MARKER_THICKNESS_M:.9g}" '
            f'pos="{_fmt(centre)}" quat="{_fmt(q)}" material="marker{m.id}_mat" contype="0" conaffinity="0" '
            f'mass="0"/>\n'
            f'<site name="marker{m.id}" pos="{_fmt(pos)}" quat="{_fmt(q)}" size="0.005" rgba="0 0 0 0"/>'))
    for index, c in enumerate(cameras):
        pos, R_b_c = c.true_mount(mount_rng(seed, "camera", index))
        R = R_b_c @ CV_TO_MUJOCO_CAM  # MuJoCo camera axes in the body
        xml = _insert_in_body(xml, c.body, (
            f'<camera name="cam_{c.name}" pos="{_fmt(pos)}" xyaxes="{_fmt(R[:, 0])} {_fmt(R[:, 1])}" '
            f'fovy="{c.fovy_deg:.9g}"/>'))
    if asset_lines:
        xml = xml.replace("<worldbody>", "<asset>\n" + "\n".join(asset_lines) + "\n  </asset>\n  <worldbody>", 1)
    if scene is not None and scene.active:
        xml, more = scene_mjcf(xml, scene, seed, exclude_ids=tuple(ids), marker_emission=emission)
        assets.update(more)
    width = max([c.width_px for c in cameras] + [min_offscreen[0]])
    height = max([c.height_px for c in cameras] + [min_offscreen[1]])
    return _ensure_offscreen(xml, width, height), assets


def fast_renderer(model: mujoco.MjModel, height_px: int, width_px: int, shadows: bool = False) -> mujoco.Renderer:
    """An offscreen renderer; without shadows and reflections unless asked: on the CPU (osmesa)
    they cost most of a frame)."""
    renderer = mujoco.Renderer(model, height_px, width_px)
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = shadows
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = shadows
    return renderer


@dataclass(frozen=True)
class FrameTruth:
    """The world at a frame's capture: the camera's pose (OpenCV axes, ``p_w = R_wc p_c + p_wc``)
    and every marker's (``R_wm``, ``p_wm``) by id."""

    R_wc: np.ndarray
    p_wc_m: np.ndarray
    markers: dict[int, tuple[np.ndarray, np.ndarray]]

    def marker_in_camera(self, marker_id: int) -> tuple[np.ndarray, np.ndarray]:
        """``(R_cm, t_cm_m)``: the true pose PnP estimates (the report's ``T_L^C``)."""
        R_wm, p_wm = self.markers[marker_id]
        return self.R_wc.T @ R_wm, self.R_wc.T @ (p_wm - self.p_wc_m)


@dataclass(frozen=True)
class CapturedFrame:
    """A frame as the companion receives it, with the SITL's ground truth at its capture."""

    frame: CameraFrame
    truth: FrameTruth
    camera_index: int


def pixel_maps(true: CameraIntrinsics, rendered: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the image a camera of intrinsics ``true`` takes (its lens' distortion
    included), where the same ray lies in the pinhole image rendered with ``rendered``
    (``cv2.remap``'s maps, x and y)."""
    u, v = np.meshgrid(np.arange(true.width_px, dtype=np.float64), np.arange(true.height_px, dtype=np.float64))
    pts = np.stack((u.ravel(), v.ravel()), axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, true.K, true.dist, P=rendered.K).reshape(true.height_px, true.width_px, 2)
    return und[..., 0].astype(np.float32), und[..., 1].astype(np.float32)


class Delivery:
    """When a camera's frames are delivered: ``latency_s`` plus a jitter drawn with ``rng``
    (:meth:`~sitl.cameras.config.CameraMount.latency_jitter_draw`) after capture, and never before
    the camera's previous frame (a camera's frames stay in capture order)."""

    def __init__(self, mount: CameraMount, rng: np.random.Generator):
        self.mount, self.rng = mount, rng
        self.last_s = -np.inf

    def available_s(self, t_capture_s: float) -> float:
        """The delivery time of the next frame, captured at ``t_capture_s``."""
        m = self.mount
        self.last_s = max(t_capture_s + m.latency_s + m.latency_jitter_draw(self.rng), self.last_s)
        return self.last_s


class _Camera:
    """One camera's renderer and schedule inside :class:`CameraRig`."""

    def __init__(self, model: mujoco.MjModel, mount: CameraMount, index: int, period_ticks: int, dt_s: float,
                 seed: int, shadows: bool = False):
        self.mount = mount
        self.index = index
        self.intr = mount.intrinsics()  # what the frames say (the estimator's calibration)
        self.true_intr = mount.true_intrinsics(np.random.default_rng([seed, 0xCA11B, index]))  # what the lens does
        self.drop_rng = np.random.default_rng([seed, 0xD409, index])
        self.delivery = Delivery(mount, np.random.default_rng([seed, 0x717E, index]))
        self.response = (SensorResponse(mount, self.true_intr, np.random.default_rng([seed, 0x6A17, index]))
                         if mount.photometric else None)
        self.cam_id = model.camera(f"cam_{mount.name}").id
        self.renderer = fast_renderer(model, mount.height_px, mount.width_px, shadows=shadows)
        self.period = period_ticks
        n = mount.blur_samples if mount.exposure_s > 0 else 1
        exposure_ticks = min(int(round(mount.exposure_s / dt_s)), period_ticks - 1)
        # ticks before the capture tick at which the exposure's renders are taken (last: 0)
        self.offsets = sorted({int(round(exposure_ticks * (n - 1 - j) / max(n - 1, 1))) for j in range(n)},
                              reverse=True)
        self.rng = np.random.default_rng([seed, 0xCA3E7A, index])
        self.acc: np.ndarray | None = None
        self.first_t = 0.0
        self.n_acc = 0
        self.seq = 0
        rendered = replace(self.intr, dist_coeffs=())  # MuJoCo's pinhole camera (its fovy)
        self.maps = pixel_maps(self.true_intr, rendered) if self.true_intr != rendered else None
        self.R_cv_to_mj = CV_TO_MUJOCO_CAM

    def render(self, data: mujoco.MjData) -> np.ndarray:
        self.renderer.update_scene(data, camera=self.cam_id)
        return self.renderer.render()

    def finish(self, t_capture_s: float) -> np.ndarray:
        """The captured image: mean of the exposure's renders, distorted, through the sensor's
        response at ``t_capture_s`` (vignetting and gain, noise, tone curve), uint8 RGB."""
        img = self.acc / self.n_acc if self.n_acc > 1 else self.acc
        self.acc, self.n_acc = None, 0
        if self.maps is not None:
            img = cv2.remap(np.ascontiguousarray(img, dtype=np.float32), self.maps[0], self.maps[1],
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if self.response is not None:
            img = self.response.expose(img, t_capture_s)
        std = self.mount.noise_std_dn
        if std > 0:
            img = img + std * self.rng.standard_normal(img.shape, dtype=np.float32)
        if self.response is not None:
            return self.response.tone(img)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


class CameraRig:
    """Every camera of a scenario on one MuJoCo model (see the module docstring).

    Call :meth:`on_tick` at every physics tick ``k`` once the kinematics of that instant are
    computed (after ``mj_step1``); :meth:`poll` returns the frames available at a time.
    ``seed``: the cameras' random streams (calibration, noise, losses, jitter, gain: each its own
    per camera, independent of the other sensors). ``scene``: the scenario's ``[scene]`` (the model
    built with it by :func:`vision_mjcf`): its shadows, and its sun dimmed by clouds at every
    render (the model's ``sun`` light, which a video rendered from the same model shows too)."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, cameras: tuple[CameraMount, ...],
                 markers: tuple[MarkerMount, ...], dt_s: float, seed: int, scene: SceneConfig | None = None):
        require_rendering()
        self.model, self.data, self.dt = model, data, dt_s
        self.marker_sites = {m.id: model.site(f"marker{m.id}").id for m in markers}
        self.sun: SunSchedule | None = None
        if scene is not None and scene.lighting.enabled and scene.lighting.cloud_cover > 0:
            self.sun = SunSchedule(scene.lighting, scene_rng(seed, "clouds"))
            self.sun_id = model.light("sun").id
            self.sun_clear = (model.light_diffuse[self.sun_id].copy(), model.light_specular[self.sun_id].copy())
        shadows = scene is not None and scene.shadows
        self.cameras: list[_Camera] = []
        try:
            for i, c in enumerate(cameras):
                period = int(round(1.0 / (c.rate_hz * dt_s)))
                if period < 1 or abs(period * c.rate_hz * dt_s - 1.0) > 1e-9:
                    raise ValueError(f"cameras[{i}].rate_hz: {c.rate_hz} Hz is not a whole divisor of the physics "
                                     f"rate {1.0 / dt_s:g} Hz")
                self.cameras.append(_Camera(model, c, i, period, dt_s, seed, shadows))
        except BaseException:
            self.close()
            raise
        #: frames lost on their way, per camera (``drop_probability``)
        self.dropped = {c.name: 0 for c in cameras}
        self.pending: deque[CapturedFrame] = deque()
        self.latest: dict[int, CapturedFrame] = {}
        self.render_s = 0.0
        self.renders = 0

    def truth(self, cam: _Camera) -> FrameTruth:
        d = self.data
        R_w_mj = d.cam_xmat[cam.cam_id].reshape(3, 3)
        markers = {i: (d.site_xmat[s].reshape(3, 3).copy(), d.site_xpos[s].copy()) for i, s in self.marker_sites.items()}
        return FrameTruth(R_w_mj @ CV_TO_MUJOCO_CAM, d.cam_xpos[cam.cam_id].copy(), markers)

    def on_tick(self, k: int, t_s: float) -> None:
        for cam in self.cameras:
            for off in cam.offsets:
                if (k + off) % cam.period:
                    continue
                w0 = time.perf_counter()
                if self.sun is not None:
                    self.light(t_s)
                img = cam.render(self.data)
                self.render_s += time.perf_counter() - w0
                self.renders += 1
                if cam.acc is None:
                    cam.acc = img.astype(np.float32) if len(cam.offsets) > 1 else img
                    cam.first_t = t_s
                else:
                    cam.acc += img
                cam.n_acc += 1
                if off == 0:
                    self._capture(cam, t_s)

    def light(self, t_s: float) -> None:
        """The sun as the clouds leave it at ``t_s`` (the model's ``sun`` light)."""
        f = self.sun.factor(t_s)
        self.model.light_diffuse[self.sun_id] = f * self.sun_clear[0]
        self.model.light_specular[self.sun_id] = f * self.sun_clear[1]

    def _capture(self, cam: _Camera, t_s: float) -> None:
        m = cam.mount
        t_capture = 0.5 * (cam.first_t + t_s)  # mid-exposure (of the renders taken)
        header = CameraFrameHeader(camera=m.name, vehicle=m.vehicle_index(), seq=cam.seq, t_capture_s=t_capture,
                                   t_available_s=cam.delivery.available_s(t_capture), width_px=m.width_px,
                                   height_px=m.height_px, encoding="rgb8", intrinsics=cam.intr)
        cam.seq += 1
        image = cam.finish(t_capture)
        if m.drop_probability and cam.drop_rng.random() < m.drop_probability:
            self.dropped[m.name] += 1  # lost on its way (its sequence number skipped, as on a real link)
            return
        self.pending.append(CapturedFrame(CameraFrame(header, image), self.truth(cam), cam.index))

    def poll(self, t_s: float) -> list[CapturedFrame]:
        """The frames that became available by ``t_s`` (capture time plus latency and jitter), in
        the order they became available (a camera's in capture order)."""
        out = [f for f in self.pending if f.frame.header.t_available_s <= t_s + 1e-12]
        if out:
            self.pending = deque(f for f in self.pending if f.frame.header.t_available_s > t_s + 1e-12)
            for f in out:
                self.latest[f.camera_index] = f
        return sorted(out, key=lambda f: f.frame.header.t_available_s)

    def close(self) -> None:
        for cam in self.cameras:
            cam.renderer.close()
        self.cameras = []

    def __enter__(self) -> CameraRig:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
