"""The slung-load flight's plots."""

from __future__ import annotations

from pathlib import Path

from companion.load.metrics import pose_error_series

__all__ = ["write_load_plots"]


def write_load_plots(load: dict, vision: dict | None, out_dir: Path, settle_s: float) -> None:
    """``load_pose_error.png`` (the report's Figs. 4, 9: EKF, UKF, unfiltered against the truth)
    and ``pnp_error.png`` (Figs. 3, 7, 8: every PnP method's error over time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if "load_t" in load:
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        t = load["load_t"]
        for kind in (k for k in ("ekf", "ukf") if f"load_{k}_p" in load):
            pe, ae = pose_error_series(load[f"load_{kind}_p"], load[f"load_{kind}_q"], load["load_p_true"],
                                       load["load_q_true"])
            axes[0].plot(t, 100 * pe, lw=0.8, label=kind.upper())
            axes[1].plot(t, ae, lw=0.8, label=kind.upper())
        if "load_unf_t" in load:
            pe, ae = pose_error_series(load["load_unf_p"], load["load_unf_q"], load["load_unf_p_true"],
                                       load["load_unf_q_true"])
            axes[0].plot(load["load_unf_t"], 100 * pe, ".", ms=2, label="unfiltered")
            axes[1].plot(load["load_unf_t"], ae, ".", ms=2, label="unfiltered")
        for ax in axes:
            ax.axvline(settle_s, color="gray", lw=0.5)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        axes[0].set(ylabel="load position error [cm]", title="slung load: pose error (report Figs. 4, 9)")
        axes[1].set(ylabel="orientation error [deg]", xlabel="t [s]")
        fig.tight_layout()
        fig.savefig(out_dir / "load_pose_error.png", dpi=110)
        plt.close(fig)
    if vision is not None and len(vision["vision_t"]):
        fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        for j, m in enumerate(vision["vision_methods"]):
            sel = vision["vision_method"] == j
            axes[0].semilogy(vision["vision_t"][sel], vision["vision_pos_err_m"][sel], ".", ms=2, label=str(m))
            axes[1].semilogy(vision["vision_t"][sel], vision["vision_att_err_deg"][sel], ".", ms=2, label=str(m))
        axes[0].set(ylabel="translation error [m] (eq. 2)", title="PnP of the load's marker (report Figs. 3, 7, 8)")
        axes[1].set(ylabel="geodesic angle [deg] (eq. 3)", xlabel="t [s]")
        for ax in axes:
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8, markerscale=4)
        fig.tight_layout()
        fig.savefig(out_dir / "pnp_error.png", dpi=110)
        plt.close(fig)
