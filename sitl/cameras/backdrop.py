"""The ``[scene]`` (:mod:`sitl.cameras.scene`) in the generated MJCF: the ground's colour or
texture, the sun and the sky, the clutter and its distractor markers.

:func:`scene_mjcf` edits the model :func:`sitl.plant.model.build_mjcf` writes (its ``ground``
plane, its ``sun`` light, its ``<visual>``) and returns the PNG assets it names. The clutter's
geoms are visual only (``contype`` and ``conaffinity`` 0): the physics is the same with or
without them. The light's change over time is applied at each render
(:class:`~sitl.cameras.photometry.SunSchedule`, by :class:`~sitl.cameras.rig.CameraRig`).
"""

from __future__ import annotations

import math
import re

import cv2
import numpy as np

from companion.vision.markers import marker_image

from .scene import ClutterItem, SceneConfig, scene_rng

__all__ = ["scene_mjcf", "ground_texture", "SUN_SPECULAR"]

#: the sun's specular intensity per unit of its diffuse intensity
SUN_SPECULAR = 0.3
#: side of the generated ground texture [px]
_GROUND_PX = 256
#: thickness of a distractor marker's plate, and its height above the crate's top [m]
_PLATE_M = 0.001
_PLATE_GAP_M = 0.002


def _fmt(v) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(v))


def _png(rgb: np.ndarray) -> bytes:
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return png.tobytes()


def ground_texture(scene: SceneConfig, rng: np.random.Generator, size_px: int = _GROUND_PX) -> np.ndarray:
    """A tileable ground texture (``size_px`` square, uint8 RGB) drawn with ``rng``: patches of
    ``ground_rgb`` and ``ground_rgb2`` (white noise filtered to a ``1/f`` spectrum, periodic, so
    the tiles join without seams) with a fine grain on top."""
    w = rng.standard_normal((size_px, size_px))
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(size_px), np.fft.fftfreq(size_px), indexing="ij"))
    f[0, 0] = np.inf
    field = np.real(np.fft.ifft2(np.fft.fft2(w) / f))
    field = (field - field.mean()) / field.std()
    mix = 1.0 / (1.0 + np.exp(-2.0 * field))  # patches in [0, 1]
    grain = 1.0 + 0.08 * rng.standard_normal((size_px, size_px))
    rgb = ((1.0 - mix)[..., None] * np.asarray(scene.ground_rgb) + mix[..., None] * np.asarray(scene.ground_rgb2))
    return np.clip(np.rint(255.0 * rgb * grain[..., None]), 0, 255).astype(np.uint8)


def _ground(xml: str, scene: SceneConfig, seed: int, assets: dict[str, bytes], asset_lines: list[str]) -> str:
    m = re.search(r'<geom name="ground"[^>]*/>', xml)
    if m is None:
        raise ValueError("scene: the model has no ground plane (geom \"ground\")")
    geom = re.sub(r'\s*rgba="[^"]*"', "", m.group(0))
    if scene.ground == "plain":
        geom = geom.replace("/>", f' rgba="{_fmt(scene.ground_rgb)} 1"/>')
    else:
        rgb1, rgb2 = _fmt(scene.ground_rgb), _fmt(scene.ground_rgb2)
        if scene.ground == "checker":
            asset_lines.append(f'    <texture name="scene_ground_tex" type="2d" builtin="checker" rgb1="{rgb1}" '
                               f'rgb2="{rgb2}" width="{_GROUND_PX}" height="{_GROUND_PX}"/>')
        else:
            assets["scene_ground.png"] = _png(ground_texture(scene, scene_rng(seed, "ground")))
            asset_lines.append('    <texture name="scene_ground_tex" type="2d" file="scene_ground.png"/>')
        rep = 1.0 / scene.ground_tile_m
        asset_lines.append(f'    <material name="scene_ground_mat" texture="scene_ground_tex" texrepeat="{rep:.9g} '
                           f'{rep:.9g}" texuniform="true" specular="0.05" shininess="0" reflectance="0"/>')
        geom = geom.replace("/>", ' material="scene_ground_mat" rgba="1 1 1 1"/>')
    return xml[: m.start()] + geom + xml[m.end():]


def _lighting(xml: str, scene: SceneConfig, seed: int) -> str:
    cfg = scene.lighting
    d = cfg.sun_direction(scene_rng(seed, "sun"))
    i = cfg.sun_intensity
    sun = (f'<light name="sun" pos="{_fmt(-20.0 * d)}" dir="{_fmt(d)}" directional="true" castshadow="true" '
           f'diffuse="{i:.9g} {i:.9g} {i:.9g}" specular="{_fmt([SUN_SPECULAR * i] * 3)}" ambient="0 0 0"/>')
    xml, n = re.subn(r'<light name="sun"[^>]*/>', sun, xml, count=1)
    if not n:
        raise ValueError("scene: the model has no light \"sun\"")
    a = cfg.sky_ambient
    headlight = f'<headlight ambient="{a:.9g} {a:.9g} {a:.9g}" diffuse="0 0 0" specular="0 0 0"/>'
    if "<visual>" in xml:
        return xml.replace("<visual>", "<visual>" + headlight, 1)
    return xml.replace("<worldbody>", f"<visual>{headlight}</visual>\n  <worldbody>", 1)


def _clutter_geoms(items: tuple[ClutterItem, ...], emission: float, assets: dict[str, bytes],
                   asset_lines: list[str], dictionary: str) -> list[str]:
    out = []
    for j, it in enumerate(items):
        q = _fmt([math.cos(0.5 * it.yaw_rad), 0.0, 0.0, math.sin(0.5 * it.yaw_rad)])
        size = _fmt(it.half_m[::2]) if it.kind == "cylinder" else _fmt(it.half_m)
        kind = "cylinder" if it.kind == "cylinder" else "box"
        out.append(f'<geom name="clutter{j}" type="{kind}" size="{size}" pos="{_fmt(it.pos_w_m)}" quat="{q}" '
                   f'rgba="{_fmt(it.rgb)} 1" contype="0" conaffinity="0"/>')
        if it.kind != "crate":
            continue
        img, fraction = marker_image(dictionary, it.marker_id, bit_px=32, quiet_zone_bits=1)
        name = f"clutter_marker{it.marker_id}"
        assets[f"{name}.png"] = _png(cv2.cvtColor(img, cv2.COLOR_GRAY2RGB))
        asset_lines += [f'    <texture name="{name}_tex" type="2d" file="{name}.png"/>',
                        f'    <material name="{name}_mat" texture="{name}_tex" texrepeat="1 1" texuniform="false" '
                        f'specular="0" shininess="0" reflectance="0" emission="{emission:.9g}"/>']
        half = 0.5 * it.marker_size_m / fraction
        top = it.pos_w_m[2] + it.half_m[2] + _PLATE_GAP_M + 0.5 * _PLATE_M
        out.append(f'<geom name="clutter{j}_marker" type="box" size="{half:.9g} {half:.9g} {0.5 * _PLATE_M:.9g}" '
                   f'pos="{_fmt([it.pos_w_m[0], it.pos_w_m[1], top])}" quat="{q}" material="{name}_mat" '
                   f'contype="0" conaffinity="0"/>')
    return out


def scene_mjcf(xml: str, scene: SceneConfig, seed: int, exclude_ids: tuple[int, ...] = (),
               marker_emission: float = 0.0) -> tuple[str, dict[str, bytes]]:
    """``xml`` with ``scene`` (module docstring), its random parts drawn from ``seed``; the
    distractor markers never take an id of ``exclude_ids`` and glow with ``marker_emission`` (as
    the scenario's own markers). Returns the MJCF and the PNG assets it names."""
    assets: dict[str, bytes] = {}
    asset_lines: list[str] = []
    xml = _ground(xml, scene, seed, assets, asset_lines)
    if scene.lighting.enabled:
        xml = _lighting(xml, scene, seed)
    clutter = scene.clutter
    if clutter.active:
        items = clutter.place(scene_rng(seed, "clutter"), exclude_ids)
        geoms = _clutter_geoms(items, marker_emission, assets, asset_lines, clutter.dictionary)
        xml = xml.replace("<worldbody>", "<worldbody>\n" + "\n".join(geoms), 1)
    if asset_lines:
        xml = xml.replace("<worldbody>", "<asset>\n" + "\n".join(asset_lines) + "\n  </asset>\n  <worldbody>", 1)
    return xml, assets
