"""What the view draws that does not move with the log: the links' bodies and rotors, how the
links hang together, the load, the markers and the cameras (:class:`SceneSpec`), from a
scenario or, for a run folder without a readable ``scenario.toml``, from the log alone."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["SceneSpec", "MarkerSpec", "CameraSpec", "spec_of_scenario", "spec_of_run"]

_log = logging.getLogger(__name__)

#: the geometry of Table 2.1 (rotor positions and thrust directions, body frame) when no scenario says
_DEFAULT_LINK_LENGTH_M = 1.0


@dataclass(frozen=True)
class MarkerSpec:
    """A fiducial marker on ``body`` (``world`` or ``load``): a ``size_m`` square centred at
    ``p_b_m``, facing ``normal_b`` with its x axis along ``right_b`` (in the body's frame)."""

    id: int
    body: str
    size_m: float
    p_b_m: tuple[float, float, float]
    normal_b: tuple[float, float, float]
    right_b: tuple[float, float, float]


@dataclass(frozen=True)
class CameraSpec:
    """Camera ``index`` of the scenario's ``[[cameras]]`` on 0-based link ``link``: at ``p_b_m`` in
    its body frame, ``R_b_c`` its OpenCV axes (x right, y down, z along the optical axis) in the
    body frame, vertical field of view ``fovy_rad`` and ``aspect`` (width / height)."""

    index: int
    name: str
    link: int
    p_b_m: tuple[float, float, float]
    R_b_c: np.ndarray
    fovy_rad: float
    aspect: float


@dataclass(frozen=True)
class SceneSpec:
    """The fixed part of the scene: ``n`` links of ``link_length_m`` along their body x axis with
    radius ``bar_radius_m``, their rotors (positions and unit thrust directions in the body frame,
    (8, 3) each), ``joined`` whether link i's right tip and link i+1's left tip are one joint
    (a chain) and ``d_b_m`` (n, 3) each link's centre-to-right-tip vector; the load's box
    (``load_size_m``, ``None``: no load) and its cable points (``load_attach_b_m``, (n, 3));
    markers, cameras and a wall; ``kind`` the scenario's kind."""

    n: int
    link_length_m: float = _DEFAULT_LINK_LENGTH_M
    bar_radius_m: float = 0.04
    rotor_positions_b_m: np.ndarray | None = None
    rotor_directions_b: np.ndarray | None = None
    rotor_radius_m: float = 0.09
    joined: bool = True
    d_b_m: np.ndarray | None = None
    load_size_m: tuple[float, float, float] | None = None
    load_attach_b_m: np.ndarray | None = None
    markers: tuple[MarkerSpec, ...] = ()
    cameras: tuple[CameraSpec, ...] = field(default_factory=tuple)
    #: a wall to push on: a point of its face and its unit normal (pointing into it), world frame
    wall: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    kind: str = "chain"

    def tips(self) -> np.ndarray:
        """(n, 3) each link's centre-to-right-tip vector in its body frame."""
        if self.d_b_m is not None:
            return np.asarray(self.d_b_m, dtype=float)
        return np.tile([0.5 * self.link_length_m, 0.0, 0.0], (self.n, 1))


def spec_of_scenario(sc) -> SceneSpec:
    """The scene of scenario ``sc`` (a :class:`~sitl.scenario.Scenario` of any kind)."""
    sk = sc.skeleton
    geometry = sc.geometry()
    markers = tuple(MarkerSpec(m.id, m.body, float(m.size_m), tuple(m.pos_b_m), tuple(m.normal_b), tuple(m.right_b))
                    for m in sc.markers)
    cameras = []
    for index, c in enumerate(sc.cameras):
        link = c.vehicle_index() if c.body.startswith("link") else -1
        if 0 <= link < sk.n_links:
            cameras.append(CameraSpec(index, c.name, link, tuple(c.pos_b_m), c.R_b_c(), float(np.radians(c.fovy_deg)),
                                      c.width_px / c.height_px))
    load = getattr(sc, "load", None)
    contact = getattr(sc, "contact", None)
    return SceneSpec(
        n=sk.n_links, link_length_m=float(sk.link_length_m), bar_radius_m=float(sk.bar_radius_m),
        rotor_positions_b_m=np.asarray(geometry.positions_m, dtype=float),
        rotor_directions_b=np.asarray(geometry.directions, dtype=float),
        joined=load is None and sk.n_links > 1, d_b_m=sk.d_b_m,
        load_size_m=tuple(load.size_m) if load is not None else None,
        load_attach_b_m=load.attach_b_m() if load is not None else None,
        markers=markers, cameras=tuple(cameras), kind=getattr(sc, "kind", "chain"),
        wall=(tuple(contact.wall_point_w_m), tuple(contact.normal_w)) if contact is not None else None)


def spec_of_run(run_dir: str | Path, n: int) -> SceneSpec:
    """The scene of run folder ``run_dir`` from its ``scenario.toml``; a plain chain of ``n``
    links (the log's) when the file is missing or unreadable (logged), or names another count."""
    path = Path(run_dir) / "scenario.toml"
    if path.is_file():
        from sitl.scenarios import load  # (the schemas only: no MuJoCo)

        try:
            _, sc = load(path)
        except Exception as exc:  # noqa: BLE001 (a damaged file: the log still shows)
            _log.warning("%s: %s; the links are drawn with the default geometry", path, exc)
        else:
            if sc.skeleton.n_links == n:
                return spec_of_scenario(sc)
            _log.warning("%s: %d links, the log has %d; drawn with the default geometry", path, sc.skeleton.n_links, n)
    return SceneSpec(n=n, joined=n > 1)
