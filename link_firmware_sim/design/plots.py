"""Fig. 2-2: the feasible control force and torque volumes ``V_F``, ``V_M`` of a design (matplotlib, the sim extra).

Imported by the CLI only when it plots, so the firmware's base install never needs matplotlib.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from .metrics import OdarDesign

__all__ = ["plot_volumes"]


def _hull_faces(points: np.ndarray) -> list[np.ndarray]:
    hull = ConvexHull(points)
    return [points[simplex] for simplex in hull.simplices]


def _sphere(ax, radius: float, color: str) -> None:
    a, b = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    ax.plot_wireframe(radius * np.cos(a) * np.sin(b), radius * np.sin(a) * np.sin(b), radius * np.cos(b),
                      color=color, linewidth=0.4, alpha=0.6)


def plot_volumes(designs: dict[str, OdarDesign], path: str | Path) -> Path:
    """One row per design: ``V_F`` [N] and ``V_M`` [Nm] with the guaranteed-wrench balls (radii F_min, M_min).

    ``designs``: title -> design. Writes a PNG at ``path`` and returns it.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(11, 5 * len(designs)))
    for row, (title, design) in enumerate(designs.items()):
        m = design.metrics()
        lam = design.problem.thrust_max_n
        panels = (
            (design.force_volume_vertices_n(), m.f_min * lam, "force f [N]", "tab:blue",
             f"$V_F$, $F_{{min}}$ = {m.f_min:.3g} $\\lambda_{{max}}$ = {m.f_min * lam:.1f} N"),
            (design.torque_volume_vertices_nm(), m.m_min * lam, "torque tau [Nm]", "tab:orange",
             f"$V_M$, $M_{{min}}$ = {m.m_min:.3g} $\\lambda_{{max}}$ = {m.m_min * lam:.2f} Nm"),
        )
        for col, (pts, radius, unit, color, label) in enumerate(panels):
            ax = fig.add_subplot(len(designs), 2, 2 * row + col + 1, projection="3d")
            ax.add_collection3d(Poly3DCollection(_hull_faces(pts), facecolor=color, edgecolor="k", linewidth=0.2,
                                                 alpha=0.25))
            _sphere(ax, radius, "k")
            lim = float(np.max(np.abs(pts)))
            for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
                setter(-lim, lim)
            ax.set_box_aspect((1, 1, 1))
            ax.set_xlabel(f"X_B {unit}")
            ax.set_ylabel("Y_B")
            ax.set_zlabel("Z_B")
            ax.set_title(f"{title}\n{label}", fontsize=9)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
