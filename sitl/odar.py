"""One ODAR link's controllers in SITL (issue 17): the SE(3) tracking comparison and the wall push.

``python -m sitl.odar compare --config configs/sitl/single_odar_figure8.toml``
    flies the scenario once per controller (``impedance``: eq. 1; ``se3_pid``: thesis sec.
    2.3.2) and reports the RMS position and attitude tracking on the figure eight (from the end of
    its amplitude ramp), against the truth and against the estimate the controller uses.

``python -m sitl.odar wall --config configs/sitl/odar/wall_push.toml``
    the contact scenario (:mod:`sitl.contact`): one ODAR pushes on a wall with a commanded normal
    force under the hybrid pose/wrench controller of sec. 2.3.3.

``python -m sitl.odar pspm [--mujoco [--config configs/sitl/odar/pspm_jump.toml]]``
    PSPM teleoperation (thesis sec. 2.3.4, :mod:`link_firmware_sim.pspm`): a scripted master
    device jumps the set position by 1 m and the set attitude by 60 deg of yaw; the ODAR runs the
    slave law with and without PSPM. Without ``--mujoco`` the ODAR is a rigid body (2.7) with the
    rotors' first-order lag and PSPM runs beside it; with ``--mujoco`` it is the full SITL flight
    (:mod:`sitl.teleop`: MuJoCo, sensors, EKF, and PSPM inside the firmware, ``SKL_PSPM_EN``).
    Reports overshoot and settling, the reservoirs' minimum, and plots the modulated set pose, the
    reservoir energies and the operator's haptic force.

Every command writes its artefacts (``metrics.json``, ``log.npz`` per run, plots) to one folder,
``runs/<command>-<scenario>-<time>/`` unless ``--out`` names one.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.estimation.so3 import attitude_error

from .runner import BatchRunner
from .scenario import Scenario, load_scenario

__all__ = ["compare_controllers", "tracking_metrics", "pspm_jump", "main"]

log = logging.getLogger(__name__)

CONTROLLERS = ("impedance", "se3_pid")


def tracking_metrics(arrays: dict[str, np.ndarray], start_s: float) -> dict:
    """RMS tracking of link 1 from ``start_s``: position [m] against the truth and the control
    estimate, attitude [deg] against the truth; max position error [m]."""
    w = arrays["t"] >= start_s
    tgt_p, tgt_q = arrays["p_target"][w, 0], arrays["q_target"][w, 0]
    pos_true = np.linalg.norm(arrays["p_true"][w, 0] - tgt_p, axis=-1)
    pos_est = np.linalg.norm(arrays["p_ctrl"][w, 0] - tgt_p, axis=-1)
    att = np.degrees(np.linalg.norm(attitude_error(arrays["q_true"][w, 0], tgt_q), axis=-1))
    rms = lambda x: float(np.sqrt(np.mean(x * x)))  # noqa: E731
    return {"rms_pos_true_m": rms(pos_true), "rms_pos_est_m": rms(pos_est), "rms_att_true_deg": rms(att),
            "max_pos_true_m": float(pos_true.max()), "window_s": [float(start_s), float(arrays["t"][-1])]}


def compare_controllers(scenario: Scenario, out_dir: Path | None, controllers=CONTROLLERS, progress=None) -> dict:
    """Fly ``scenario`` once per controller; their tracking metrics (and ``log.npz`` per controller)."""
    tr = scenario.trajectory
    start = tr.figure8_start_s + tr.figure8_period_s if tr.kind == "figure8" else scenario.flight_start_s
    out: dict = {"scenario": scenario.name, "seed": scenario.seed, "controllers": {}}
    for name in controllers:
        sc = replace(scenario, firmware=replace(scenario.firmware, controller=name))
        runner = BatchRunner(sc)
        runner.run(sc.duration_s, progress=progress)
        arrays = runner.arrays()
        m = tracking_metrics(arrays, start)
        m.update(took_off=runner.plant.took_off, crashed=runner.crashed, crash_reason=runner.crash_reason,
                 real_time_factor=runner.sim_s / runner.wall_s if runner.wall_s > 0 else None)
        out["controllers"][name] = m
        log.info("%s: %s", name, m)
        if out_dir is not None:
            (out_dir / name).mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out_dir / name / "log.npz", **arrays)
    if out_dir is not None:
        (out_dir / "metrics.json").write_text(json.dumps(out, indent=2) + "\n")
        _plot_compare(out_dir, controllers, start)
    return out


def _plot_compare(out_dir: Path, controllers, start_s: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_xy, ax_e) = plt.subplots(1, 2, figsize=(11, 4.5))
    for name in controllers:
        a = np.load(out_dir / name / "log.npz")
        w = a["t"] >= start_s
        ax_xy.plot(a["p_true"][w, 0, 0], a["p_true"][w, 0, 1], label=f"{name} (true)", lw=0.8)
        ax_e.plot(a["t"][w], 100 * np.linalg.norm(a["p_true"][w, 0] - a["p_target"][w, 0], axis=-1), label=name, lw=0.8)
    ax_xy.plot(a["p_target"][w, 0, 0], a["p_target"][w, 0, 1], "k--", lw=0.8, label="target")
    ax_xy.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", title="figure eight at 45 deg pitch")
    ax_e.set(xlabel="t [s]", ylabel="|p - p_d| [cm] (true)")
    for ax in (ax_xy, ax_e):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_dir / "compare_tracking.png", dpi=110)
    plt.close(fig)


def _rigid_step(p, v, R, w, U, lag_state, inertia, dt, tau_s):
    """(2.7) with a first-order lag of the rotors' wrench (semi-implicit Euler, exact rotation)."""
    from companion.estimation.so3 import quat_from_rotvec, quat_to_rotmat
    from companion.skeleton.body import GRAVITY_M_S2

    lag_state = lag_state + (1.0 - np.exp(-dt / tau_s)) * (U - lag_state)
    J = np.asarray(inertia.inertia_kgm2)
    a = R @ lag_state[:3] / inertia.mass_kg - np.array([0.0, 0.0, GRAVITY_M_S2])
    wdot = (lag_state[3:] - np.cross(w, J * w)) / J
    v = v + dt * a
    w = w + dt * wdot
    return p + dt * v, v, R @ quat_to_rotmat(quat_from_rotvec(w * dt)), w, lag_state


def pspm_jump(out_dir: Path | None, duration_s: float = 16.0, jump_m: float = 1.0, yaw_jump_deg: float = 60.0,
              operator_hz: float = 125.0, control_hz: float = 500.0, progress=None) -> dict:
    """The operator-jump scenario with and without PSPM on the rigid body (module docstring); the
    metrics and plot of :mod:`sitl.teleop` (its MuJoCo counterpart)."""
    from companion.estimation.so3 import quat_from_euler_zyx, rotmat_to_quat
    from companion.skeleton.body import SkeletonConfig, link_inertia
    from companion.skeleton.rotors import RotorGeometry
    from link_firmware_sim.pspm import (HapticGains, PspmGains, haptic_feedback, master_set_pose, pspm_init,
                                        pspm_observe, pspm_update, slave_wrench)

    from .teleop import heading_deg, jump_metrics, plot_jump

    inertia = link_inertia(SkeletonConfig(n_links=1, link_length_m=1.2, link_mass_kg=2.6), RotorGeometry.odar())
    # reservoirs start full (an empty one at rest never releases a jump: nothing dissipates); the
    # caps set how much of a jump passes at once (0.4 J: 0.27 m of the 1 m spring; 0.3 J: 18 deg)
    gains = PspmGains(e_max_t_j=0.4, e_max_r_j=0.3, e0_t_j=0.4, e0_r_j=0.3)
    haptic = HapticGains(p0_w_m=(0.0, 0.0, 2.0))
    dt = 1.0 / control_hz
    every = int(round(control_hz / operator_hz))
    t_jump, t_yaw = 2.0, 9.0
    level = np.array([1.0, 0.0, 0.0, 0.0])
    out: dict = {"model": "rigid body (2.7) with the rotors' first-order lag", "jump_m": jump_m,
                 "yaw_jump_deg": yaw_jump_deg, "operator_hz": operator_hz, "runs": {}}
    series = {}
    for modulated in (False, True):
        p, v, R, w = np.array([0.0, 0.0, 2.0]), np.zeros(3), np.eye(3), np.zeros(3)
        p0 = p.copy()
        lag = np.concatenate((np.array([0.0, 0.0, inertia.mass_kg * 9.80665]), np.zeros(3)))
        state = pspm_init(p, rotmat_to_quat(R), gains, 0.0)
        p_bar, q_bar = p.copy(), rotmat_to_quat(R)
        rec = {k: [] for k in ("t", "along_true_m", "along_d_m", "along_bar_m", "yaw_true_deg", "yaw_d_deg",
                               "yaw_bar_deg", "energy_t_j", "energy_r_j", "f_h_n", "speed_m_s")}
        n = int(round(duration_s / dt))
        for k in range(n):
            t = k * dt
            q = rotmat_to_quat(R)
            if k % every == 0:  # an operator sample (the scripted master device)
                p_h = np.array([jump_m if t >= t_jump else 0.0, 0.0, 0.0])
                q_h = quat_from_euler_zyx(np.radians(yaw_jump_deg) if t >= t_yaw else 0.0, 0.0, 0.0)
                p_d, q_d = master_set_pose(p_h, q_h, haptic)
                if modulated:
                    state = pspm_update(state, gains, p_d, q_d, p, q, t)
                    p_bar, q_bar = state.p_bar_w_m, state.q_bar_wxyz
                else:
                    p_bar, q_bar = p_d, q_d
                # the scripted master teleports (its velocity would be infinite): no device damping term
                f_h, _ = haptic_feedback(np.zeros(3), np.zeros(3), p_d, q_d, p_bar, q_bar, np.zeros(3), np.zeros(3), haptic)
                for key, value in (("t", t), ("along_true_m", p[0] - p0[0]), ("along_d_m", p_d[0] - p0[0]),
                                   ("along_bar_m", p_bar[0] - p0[0]), ("yaw_true_deg", heading_deg(q, level)),
                                   ("yaw_d_deg", heading_deg(q_d, level)), ("yaw_bar_deg", heading_deg(q_bar, level)),
                                   ("energy_t_j", state.energy_t_j if modulated else np.nan),
                                   ("energy_r_j", state.energy_r_j if modulated else np.nan),
                                   ("f_h_n", f_h.copy()), ("speed_m_s", float(np.linalg.norm(v)))):
                    rec[key].append(value)
            U = slave_wrench(p, v, q, w, p_bar, q_bar, gains, inertia.mass_kg)
            p, v, R, w, lag = _rigid_step(p, v, R, w, U, lag, inertia, dt, 0.05)
            if modulated:
                state = pspm_observe(state, gains, p, w, dt)
            if progress is not None and k % 50 == 49:
                progress(50 * dt)
        rec = {k: np.asarray(x) for k, x in rec.items()}
        rec["axis"] = np.array([1.0, 0.0, 0.0])
        name = "pspm" if modulated else "unmodulated"
        out["runs"][name] = jump_metrics(rec["t"], rec["along_true_m"], rec["yaw_true_deg"], rec["energy_t_j"],
                                         rec["energy_r_j"], rec["speed_m_s"], jump_m, t_jump, yaw_jump_deg, t_yaw)
        series[name] = rec
    if out_dir is not None:
        (out_dir / "metrics.json").write_text(json.dumps(out, indent=2) + "\n")
        np.savez_compressed(out_dir / "log.npz", **{f"{n}_{k}": v for n, r in series.items() for k, v in r.items()})
        plot_jump(series, out_dir / "pspm_jump.png", jump_m, yaw_jump_deg, "rigid body")
    return out


def _out_dir(arg: str | None, command: str, name: str) -> Path:
    out = Path(arg) if arg else Path("runs") / f"{command}-{name}-{time.strftime('%Y%m%d-%H%M%S')}"
    out.mkdir(parents=True, exist_ok=True)
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m sitl.odar", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("compare", help="impedance (eq. 1) vs SE(3) PID (sec. 2.3.2) on a scenario")
    c.add_argument("--config", default="configs/sitl/single_odar_figure8.toml")
    w = sub.add_parser("wall", help="hybrid pose/wrench control pushing on a wall (sec. 2.3.3)")
    w.add_argument("--config", default="configs/sitl/odar/wall_push.toml")
    m = sub.add_parser("pspm", help="PSPM teleoperation: operator jumps with and without PSPM (sec. 2.3.4)")
    m.add_argument("--mujoco", action="store_true",
                   help="fly the full SITL (MuJoCo, EKF, PSPM in the firmware) instead of the rigid body")
    m.add_argument("--config", default="configs/sitl/odar/pspm_jump.toml", help="the --mujoco scenario")
    m.add_argument("--duration", type=float,
                   help="length of each run [s] (default: 16 on the rigid body, the scenario's with --mujoco)")
    m.add_argument("--jump", type=float, help="operator position jump [m] (default: 1, or the scenario's)")
    m.add_argument("--seed", type=int, help="random seed (--mujoco; default: the scenario's)")
    m.add_argument("--out", help="run folder (default: runs/pspm-<jump|scenario>-<time>)")
    for q in (c, w):
        q.add_argument("--duration", type=float, help="flight length [s] (default: the scenario's)")
        q.add_argument("--seed", type=int, help="random seed (default: the scenario's)")
        q.add_argument("--out", help="run folder (default: runs/<command>-<scenario>-<time>)")
    return p


def main(argv=None) -> int:
    from tqdm import tqdm

    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.command == "pspm" and not args.mujoco:
        out = _out_dir(args.out, "pspm", "jump")
        duration = 16.0 if args.duration is None else args.duration
        with tqdm(total=2 * duration, unit="sim s", desc="pspm") as bar:
            result = pspm_jump(out, duration_s=duration, jump_m=1.0 if args.jump is None else args.jump,
                               progress=bar.update)
        print(json.dumps(result, indent=2))
        print(f"run folder: {out}")
        return 0
    if args.command == "pspm":
        from .teleop import MODES, load_teleop_scenario, pspm_jump_mujoco

        overrides = {k: v for k, v in (("duration_s", args.duration), ("seed", args.seed)) if v is not None}
        try:
            sc = load_teleop_scenario(args.config, **overrides)
            if args.jump is not None:
                sc = replace(sc, teleop=replace(sc.teleop, jump_m=args.jump))
        except (OSError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        out = _out_dir(args.out, "pspm", sc.name)
        with tqdm(total=len(MODES) * sc.duration_s, unit="sim s", desc="pspm (MuJoCo)") as bar:
            result = pspm_jump_mujoco(sc, out, progress=bar.update)
        print(json.dumps(result, indent=2))
        print(f"run folder: {out}")
        return 0
    overrides = {k: v for k, v in (("duration_s", args.duration), ("seed", args.seed)) if v is not None}
    try:
        if args.command == "wall":
            from .contact import WallPushScenario, load_wall_scenario, wall_push

            sc: WallPushScenario = load_wall_scenario(args.config, **overrides)
        else:
            sc = load_scenario(args.config, **overrides)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = _out_dir(args.out, args.command, sc.name)
    runs = len(CONTROLLERS) if args.command == "compare" else 1
    with tqdm(total=runs * sc.duration_s, unit="sim s", desc=args.command) as bar:
        progress = lambda s: bar.update(s)  # noqa: E731
        result = (compare_controllers(sc, out, progress=progress) if args.command == "compare"
                  else wall_push(sc, out, progress=progress))
    print(json.dumps(result, indent=2))
    print(f"run folder: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
