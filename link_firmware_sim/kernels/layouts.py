"""The named slots of the firmware kernels' grouped state, defined once.

The per-tick kernels read and write a few preallocated float64 arrays instead of dozens of
arguments; each array's layout is here, as offsets (a field of several numbers starts at its
offset), so that the kernels compile them as constants and the Python that fills or reads an
array uses the same names:

* ``EKF_*``: an EKF's parameters (:attr:`~link_firmware_sim.estimators.link_ekf.LinkEkf.par`);
* ``CTL_*``: eq. 1's controller, its gains, the link's inertia and its integrals (the impedance
  controller's :attr:`~link_firmware_sim.controllers.impedance.ImpedanceController.state`);
* ``TGT_*``: a pose target as eq. 1 reads it;
* ``ALLOC_*``: the allocator's thresholds, null vector and modulation state, the rotor left out;
* ``IN_*``: the fused tick's inputs from the firmware (the correction's weight, the correction, the target);
* ``OUT_*``: the fused tick's results;
* ``IO_*``: the vehicle's side of the record tick and of the lockstep loop (what the vehicle sets,
  what the kernels report), the tick's results at its start.
"""

from __future__ import annotations

# EKF parameters: the error state's process noise densities (15), the barometer offset's, gravity
# (world, 3), the gate [sigma] and the attitude reference's covariance (3x3, row-major)
EKF_DENSITIES, EKF_BARO_DENSITY, EKF_GRAVITY_W, EKF_GATE_SIGMA, EKF_ATT_COV, EKF_SIZE = 0, 15, 16, 19, 20, 29

# eq. 1's controller: kp, kd, ki (3 each), kR, kw, kI, gamma_I, the position and attitude integrals'
# limits, the position error's limit; mass, principal inertia (3), gravity; the position (3) and
# attitude (3) integrals (updated by the kernels)
CTL_KP, CTL_KD, CTL_KI, CTL_KR, CTL_KW, CTL_KI_ATT, CTL_GAMMA_I = 0, 3, 6, 9, 10, 11, 12
CTL_POS_INT_LIMIT, CTL_ATT_INT_LIMIT, CTL_POS_ERROR_LIMIT = 13, 14, 15
CTL_MASS, CTL_J, CTL_GRAVITY, CTL_POS_INT, CTL_ATT_INT, CTL_SIZE = 16, 17, 20, 21, 24, 27

# a pose target: p_d, v_d, a_d, w_d, wdot_d (3 each), R_d (row-major, 9), f_ff, tau_ff (3 each)
TGT_P, TGT_V, TGT_A, TGT_W, TGT_WDOT, TGT_R, TGT_FORCE_FF, TGT_TORQUE_FF, TGT_SIZE = 0, 3, 6, 9, 12, 15, 24, 27, 30

# the allocator: eps0, eps1, thrust limit, selective mapping and scale-to-limit (1 or 0), the margin's
# tolerance, the null vector nu (4), the modulation's state xi''_pre (2, updated by the kernels)
ALLOC_EPS0, ALLOC_EPS1, ALLOC_TMAX, ALLOC_SELECTIVE, ALLOC_SCALE_TO_LIMIT, ALLOC_TOL = 0, 1, 2, 3, 4, 5
ALLOC_NU, ALLOC_XI_PRE, ALLOC_FAILED = 6, 10, 12
#: the removed rotor's test thrust [N] and the wrench it makes (6)
ALLOC_TEST, ALLOC_TEST_WRENCH, ALLOC_SIZE = 13, 14, 20

# the fused tick's inputs: the correction's weight, the correction [dp; dv; dtheta] (9), the target
IN_WEIGHT, IN_CORRECTION, IN_TARGET, IN_SIZE = 0, 1, 10, 10 + TGT_SIZE

# the fused tick's results: thrust commands (8), U = [u; tau] (6), |u|, the control estimate's
# position (3), 1 if U is finite (else 0), the allocation's scale and saturated (1 or 0; U finite)
OUT_COMMAND, OUT_U, OUT_FORCE_NORM, OUT_P_CTRL, OUT_FINITE, OUT_SCALE, OUT_SATURATED, OUT_SIZE = (
    0, 8, 14, 15, 18, 19, 20, 21)

# the vehicle's side: the tick's results (OUT_*, at 0); the body rate of the newest tick (FLU, 3);
# the attitude references fused: accepted, rejected, the newest one's time_usec and quaternion (body
# FLU to ENU, 4); the thrust limit and the mode the answer carries; the frame change's two quaternions
# (NED/FRD to ENU/FLU, 8)
IO_GYRO, IO_AHRS_ACCEPTED, IO_AHRS_REJECTED, IO_AHRS_T_US, IO_AHRS_Q = 21, 24, 25, 26, 27
IO_THRUST_MAX, IO_MODE, IO_FRAME = 31, 32, 33
# ... the lockstep loop's inputs: the wait [ms], the most quiet ticks, the descriptors polled, the
# previous tick's time, the nominal step [s], the target's time and staleness, the correction's time
# (NaN: none), hold and staleness, the last GPS fix and its timeout, the next stream or log row
# [us], the arming height (inf once airborne) and the take-off height above it
IO_TIMEOUT_MS, IO_MAX_TICKS, IO_N_FDS, IO_T_PREV, IO_DT_DEFAULT, IO_TARGET_TIME, IO_TARGET_STALE = (
    41, 42, 43, 44, 45, 46, 47)
IO_CORR_TIME, IO_CORR_HOLD, IO_CORR_STALE, IO_GPS_FIX, IO_GPS_TIMEOUT, IO_DUE_US = 48, 49, 50, 51, 52, 53
IO_ARM_HEIGHT, IO_TAKEOFF = 54, 55
# ... and what it reports: why it returned (LOOP_* of .lockstep), the ticks it computed, the answers
# it sent, the newest tick's time [us] and step [s], the length of a packet it left to the caller,
# the bytes of the packets it took
IO_STATUS, IO_TICKS, IO_SENT, IO_T_US, IO_DT, IO_PACKET, IO_TAKEN_BYTES = 56, 57, 58, 59, 60, 61, 62
# ... and the newest tick's specific force (FLU, 3)
IO_ACCEL, IO_SIZE = 63, 66
