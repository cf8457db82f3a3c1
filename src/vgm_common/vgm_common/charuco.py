"""The ChArUco board of the calibration chart (INTERFACES.md, "The calibration chart"):
one definition for the simulator's print and calib_node's detector. No rclpy."""

from __future__ import annotations

import cv2

DEFAULT_DICTIONARY = 'DICT_5X5_100'
DEFAULT_MARKER_FRACTION = 0.75  # marker_size 0: this fraction of the square size


def charuco_board(
    rows: int, cols: int, spacing: float, marker_size: float, dictionary: str
) -> cv2.aruco.CharucoBoard:
    """The ``cv2.aruco.CharucoBoard`` of the chart frame of INTERFACES.md: rows x cols
    inner corners ((cols + 1) x (rows + 1) squares of ``spacing`` [m], the top-left one
    black), chessboard corner id ``r * cols + c`` at inner corner (r, c); markers of
    ``marker_size`` [m] (0: ``DEFAULT_MARKER_FRACTION`` * spacing) from the
    predefined ``dictionary`` (e.g. ``DICT_5X5_100``).

    Raises:
        ValueError: an unknown dictionary (the message lists the valid ones), a marker not
            smaller than a square, or a dictionary with fewer markers than the board needs.
    """
    names = aruco_dictionary_names()
    if dictionary not in names:
        raise ValueError(f'unknown ArUco dictionary {dictionary!r}; valid: {", ".join(names)}')
    marker = marker_size or DEFAULT_MARKER_FRACTION * spacing
    if not 0 < marker < spacing:
        raise ValueError(f'marker size {marker:g} m must be in (0, square size {spacing:g} m)')
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    needed = (rows + 1) * (cols + 1) // 2
    if needed > len(aruco.bytesList):
        raise ValueError(
            f'a {rows}x{cols} ChArUco board needs {needed} markers, '
            f'{dictionary} has {len(aruco.bytesList)}'
        )
    return cv2.aruco.CharucoBoard((cols + 1, rows + 1), spacing, marker, aruco)


def aruco_dictionary_names() -> list[str]:
    """The predefined ArUco dictionaries of the pinned OpenCV (``DICT_5X5_100``, ...)."""
    return sorted(n for n in dir(cv2.aruco) if n.startswith('DICT_'))
