"""The controllers' reports: the momentum observer's SKELETON_EXTERNAL_WRENCH (hybrid controller,
``SKL_WRENCH_HZ``) and PSPM's reservoirs as DEBUG_VECT ``PSPM`` (under teleoperation,
``SKL_PSPM_EN``). Without that controller the stream sends nothing."""

from __future__ import annotations

from companion.mavlink.codec import encode_external_wrench
from companion.mavlink.dialect import load_dialect

__all__ = ["PSPM_DEBUG_NAME", "external_wrench", "pspm"]

D = load_dialect()
#: DEBUG_VECT name of PSPM's reservoirs (x: E_t, y: E_r [J]; z: the set position's lag [m])
PSPM_DEBUG_NAME = b"PSPM"


def external_wrench(v):
    """The momentum observer's estimate (``None`` without one: the stream sends nothing)."""
    report = v.fw.external_wrench_report()
    return None if report is None else encode_external_wrench(report)


def pspm(v):
    """DEBUG_VECT ``PSPM``: x, y the reservoirs E_t, E_r [J], z how far the modulated set position
    lags the operator's [m] (``None`` while PSPM is off: the stream sends nothing)."""
    report = v.fw.pspm_report()
    return None if report is None else D.MAVLink_debug_vect_message(PSPM_DEBUG_NAME, v.fc_time_us, *report)
