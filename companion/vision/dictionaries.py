"""The predefined ArUco dictionaries and their number of ids, without OpenCV (configs validate
against it on installs without the ``vision`` extra; ``tests/unit/test_vision.py`` checks it against
``cv2.aruco``)."""

from __future__ import annotations

__all__ = ["ARUCO_DICTIONARY_IDS", "check_marker"]

#: dictionary name (``cv2.aruco.<name>``) -> number of ids
ARUCO_DICTIONARY_IDS: dict[str, int] = {
    **{f"DICT_{b}X{b}_{n}": n for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000)},
    "DICT_ARUCO_ORIGINAL": 1024,
    "DICT_APRILTAG_16h5": 30,
    "DICT_APRILTAG_25h9": 35,
    "DICT_APRILTAG_36h10": 2320,
    "DICT_APRILTAG_36h11": 587,
    "DICT_ARUCO_MIP_36h12": 250,
}


def check_marker(dictionary: str, marker_id: int | None = None) -> None:
    """``ValueError`` for an unknown dictionary (message starts ``dictionary:``) or an id outside it
    (``id:``)."""
    if dictionary not in ARUCO_DICTIONARY_IDS:
        raise ValueError(f"dictionary: unknown ArUco dictionary {dictionary!r} "
                         f"(one of: {', '.join(ARUCO_DICTIONARY_IDS)})")
    n = ARUCO_DICTIONARY_IDS[dictionary]
    if marker_id is not None and not 0 <= marker_id < n:
        raise ValueError(f"id: {dictionary} has ids 0..{n - 1}, got {marker_id}")
