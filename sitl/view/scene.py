"""The 3D scene in a viser server: the nodes of a :class:`~sitl.view.spec.SceneSpec`, moved to each
:class:`~sitl.view.frame.ViewFrame`.

Node names (viser's scene tree; ``i`` counts links from 1):

- ``/ground``, ``/markers/m<id>``, ``/wall``: the ground grid, the fiducial markers, the wall to push on;
- ``/links/link<i>``: the link's true pose; under it ``body`` (the bar, coloured by the link's
  condition, :data:`CONDITION_COLORS`), ``rotor<k>`` (a disc per rotor, across its thrust
  direction), ``label`` (its name), ``camera_<name>`` (each camera's frustum);
- ``/ghosts/<kind>`` for ``ekf``, ``corrected`` and ``target``: each link's estimate or target as
  a translucent bar (:data:`GHOST_COLORS`), one batch of bars per kind;
- ``/cables``: the joints of a chain (right tip to the next link's left tip), or a slung load's
  cables (each vehicle to its point on the load);
- ``/corrections``: per link, the companion's last correction as an arrow from the estimate the
  step used towards the corrected one, its length scaled by :attr:`Scene.arrow_gain`;
- ``/load``: the load's box at its true pose.
"""

from __future__ import annotations

import numpy as np

from companion.estimation.so3 import quat_to_rotmat, rotmat_to_quat

from companion.linkstate import condition

from .frame import Poses, ViewFrame
from .spec import SceneSpec

__all__ = ["Scene", "CONDITION_COLORS", "GHOST_COLORS", "GHOSTS"]

#: a link's colour by its condition (:func:`companion.linkstate.condition`), RGB 0-255
CONDITION_COLORS = {
    "flying": (40, 110, 230),
    "disarmed": (150, 150, 150),
    "no_ekf": (150, 80, 200),
    "gps_fault": (230, 60, 160),
    "excluded": (235, 200, 20),
    "carried": (245, 140, 30),
    "down": (90, 20, 20),
}
#: the ghosts' colours, RGB 0-255
GHOST_COLORS = {"ekf": (40, 200, 90), "corrected": (0, 200, 220), "target": (200, 200, 200)}
GHOSTS = tuple(GHOST_COLORS)
_CABLE = (255, 140, 0)
_ARROW = (230, 30, 30)
_NO_POSE = np.array([0.0, 0.0, -1000.0])  # where a node without a pose waits (hidden as well)


def _box_mesh(size) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and triangles (12, 3) of a box of ``size`` (x, y, z) centred at the origin."""
    half = np.asarray(size, dtype=float) / 2.0
    vertices = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float) * half
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.uint32)
    return vertices.astype(np.float32), faces


def _unit_quat(q: np.ndarray) -> np.ndarray:
    """``q`` (..., 4) normalised; a zero (or non-finite) quaternion in a hostile log: the identity
    (:func:`companion.estimation.so3.quat_normalize` raises on it)."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    ok = np.isfinite(n) & (n > 1e-12)
    return np.where(ok, q / np.where(ok, n, 1.0), [1.0, 0.0, 0.0, 0.0])


def _z_along(direction, x_hint=None) -> np.ndarray:
    """The quaternion (w, x, y, z) of a frame whose z axis is ``direction`` and whose x axis is
    ``x_hint`` made normal to it (any normal direction without one)."""
    z = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    if x_hint is None:
        x_hint = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x = np.asarray(x_hint, dtype=float)
    x = x - z * (x @ z)
    x /= np.linalg.norm(x)
    return rotmat_to_quat(np.column_stack((x, np.cross(z, x), z)))


class Scene:
    """The nodes of ``spec`` in viser server ``server``; :meth:`show` moves them to a frame."""

    def __init__(self, server, spec: SceneSpec):
        self.server = server
        self.spec = spec
        #: the correction arrows' length per metre of correction
        self.arrow_gain = 5.0
        self.visible = {"truth": True, "ekf": True, "corrected": True, "target": True, "corrections": True,
                        "cables": True, "labels": True}
        scene = server.scene
        scene.set_up_direction("+z")
        scene.add_grid("/ground", width=20.0, height=20.0, cell_size=0.5, section_size=2.0, plane="xy")
        for m in spec.markers:
            if m.body == "world":
                scene.add_box(f"/markers/m{m.id}", color=(20, 20, 20), dimensions=(m.size_m, m.size_m, 0.004),
                              wxyz=_z_along(m.normal_b, m.right_b), position=m.p_b_m)
        if spec.wall is not None:  # a 4 m x 4 m slab behind its face
            point, normal = (np.asarray(v, dtype=float) for v in spec.wall)
            scene.add_box("/wall", color=(190, 170, 150), dimensions=(4.0, 4.0, 0.1), opacity=0.6,
                          wxyz=_z_along(normal), position=point + 0.05 * normal)
        self.links, self.bodies, self.labels = [], [], []
        self.frustums: dict = {}  # camera index -> its frustum
        L, r = spec.link_length_m, spec.bar_radius_m
        for i in range(spec.n):
            name = f"/links/link{i + 1}"
            self.links.append(scene.add_frame(name, show_axes=False, position=_NO_POSE))
            self.bodies.append(scene.add_box(f"{name}/body", color=CONDITION_COLORS["flying"],
                                             dimensions=(L, 2 * r, 2 * r)))
            if spec.rotor_positions_b_m is not None:
                for k, (pk, uk) in enumerate(zip(spec.rotor_positions_b_m, spec.rotor_directions_b)):
                    scene.add_cylinder(f"{name}/rotor{k + 1}", radius=spec.rotor_radius_m, height=0.01,
                                       color=(60, 60, 60), opacity=0.7, position=tuple(pk), wxyz=_z_along(uk))
            self.labels.append(scene.add_label(f"{name}/label", f"link {i + 1}", position=(0.0, 0.0, 0.25)))
            for c in spec.cameras:
                if c.link == i:
                    self.frustums[c.index] = scene.add_camera_frustum(f"{name}/camera_{c.name}", fov=c.fovy_rad, aspect=c.aspect, scale=0.15,
                                             color=(240, 240, 60), position=c.p_b_m, wxyz=rotmat_to_quat(c.R_b_c))
        vertices, faces = _box_mesh((L, 2.6 * r, 2.6 * r))
        self.ghosts = {kind: scene.add_batched_meshes_simple(
            f"/ghosts/{kind}", vertices, faces, batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (spec.n, 1)),
            batched_positions=np.tile(_NO_POSE, (spec.n, 1)), batched_colors=color, opacity=0.35, lod="off",
            flat_shading=True, cast_shadow=False, receive_shadow=False, visible=False)
            for kind, color in GHOST_COLORS.items()}
        self.load = None
        if spec.load_size_m is not None:
            self.load = scene.add_box("/load", color=(160, 110, 60), dimensions=spec.load_size_m, position=_NO_POSE)
        self._segments: dict[str, tuple] = {}  # node name -> (handle, segments it holds)
        self._last: ViewFrame | None = None
        self._conditions: list[str | None] = [None] * spec.n

    def set_camera_image(self, index: int, image: np.ndarray, max_width_px: int = 320) -> None:
        """Show ``image`` (rgb or mono, uint8) in camera ``index``'s frustum, thinned to at most
        ``max_width_px`` wide."""
        frustum = self.frustums.get(index)
        if frustum is None:
            return
        step = max(1, -(-image.shape[1] // max_width_px))
        frustum.image = np.ascontiguousarray(image[::step, ::step])

    def set_visible(self, what: str, on: bool) -> None:
        """Show or hide ``what`` (``truth``, a ghost kind, ``corrections``, ``cables``, ``labels``)."""
        self.visible[what] = bool(on)
        if what == "labels":
            for label in self.labels:
                label.visible = bool(on)
        if self._last is not None:
            self.show(self._last)

    def _cable_points(self, f: ViewFrame) -> np.ndarray:
        p, R = f.truth.p_w_m, quat_to_rotmat(_unit_quat(f.truth.q_wxyz))
        spec = self.spec
        if spec.joined:
            tip = np.einsum("nij,nj->ni", R, spec.tips())
            return np.stack((p[:-1] + tip[:-1], p[1:] - tip[1:]), axis=1)
        if spec.load_attach_b_m is not None and f.load is not None and f.load.known.all():
            pl = np.asarray(f.load.p_w_m, dtype=float).reshape(3)
            Rl = quat_to_rotmat(_unit_quat(np.asarray(f.load.q_wxyz, dtype=float).reshape(4)))
            return np.stack((p, pl + spec.load_attach_b_m @ Rl.T), axis=1)
        return np.zeros((0, 2, 3))

    def show(self, f: ViewFrame) -> None:
        """Move every node to frame ``f`` (as one update of the clients)."""
        self._last = f
        vis = self.visible
        with self.server.atomic():
            known = f.truth.known
            for i, link in enumerate(self.links):
                on = bool(vis["truth"] and known[i])
                if link.visible != on:
                    link.visible = on
                if on:
                    link.position = f.truth.p_w_m[i]
                    link.wxyz = _unit_quat(f.truth.q_wxyz[i])
                cond = condition(f.link_state[i]) if f.link_state is not None else "flying"
                if cond != self._conditions[i]:
                    self.bodies[i].color = CONDITION_COLORS[cond]
                    self._conditions[i] = cond
            for kind, node in self.ghosts.items():
                poses: Poses | None = getattr(f, kind)
                self._place_batch(node, poses if vis[kind] else None)
            if self.load is not None:
                self._place([self.load], f.load if f.load is not None and vis["truth"] else None)
            self._cables(f)
            self._arrows(f)

    @staticmethod
    def _place(nodes: list, poses: Poses | None) -> None:
        if poses is None:
            for node in nodes:
                node.visible = False
            return
        p = np.asarray(poses.p_w_m, dtype=float).reshape(len(nodes), 3)
        q = np.asarray(poses.q_wxyz, dtype=float).reshape(len(nodes), 4)
        known = np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1)
        for node, pk, qk, ok in zip(nodes, p, q, known):
            node.visible = bool(ok)
            if ok:
                node.position = pk
                node.wxyz = _unit_quat(qk)

    @staticmethod
    def _place_batch(node, poses: Poses | None) -> None:
        """A ghost kind's bars at ``poses`` (a link without a finite pose out of sight)."""
        if poses is None or not poses.known.any():
            if node.visible:
                node.visible = False
            return
        known = poses.known
        p = np.where(known[:, None], np.asarray(poses.p_w_m, dtype=float), _NO_POSE)
        q = _unit_quat(np.where(known[:, None], np.asarray(poses.q_wxyz, dtype=float), [1.0, 0.0, 0.0, 0.0]))
        node.batched_positions = p.astype(np.float32)
        node.batched_wxyzs = q.astype(np.float32)
        if not node.visible:
            node.visible = True

    def _cables(self, f: ViewFrame) -> None:
        pts = self._cable_points(f) if self.visible["cables"] else np.zeros((0, 2, 3))
        pts = pts[np.isfinite(pts).all(axis=(1, 2))]
        self._lines("/cables", pts, lambda p: self.server.scene.add_line_segments(
            "/cables", points=p, colors=_CABLE, thickness=0.015))

    def _arrows(self, f: ViewFrame) -> None:
        src, dst = f.correction_from_w_m, f.correction_to_w_m
        pts = np.zeros((0, 2, 3))
        if self.visible["corrections"] and src is not None and dst is not None:
            ok = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1)
            tail = src[ok]
            pts = np.stack((tail, tail + self.arrow_gain * (dst[ok] - tail)), axis=1)
        self._lines("/corrections", pts, lambda p: self.server.scene.add_arrows(
            "/corrections", points=p, colors=_ARROW, shaft_radius=0.008, head_radius=0.02, head_length=0.04))

    def _lines(self, name: str, pts: np.ndarray, make) -> None:
        """Node ``name`` (segments or arrows, (k, 2, 3) ``pts``): its points moved, made again
        (``make(points)``) when their count changes, hidden when there are none."""
        pts = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 2, 3)
        node, count = self._segments.get(name, (None, -1))
        if len(pts) and len(pts) == count:
            node.points = pts
        elif len(pts):
            self._segments[name] = (make(pts), len(pts))
        elif node is not None and count:
            node.visible = False
            self._segments[name] = (node, 0)
