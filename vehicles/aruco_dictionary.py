"""ArUco dictionaries by OpenCV name (``"DICT_4X4_50"``): the one default and the one lookup that every
marker setting uses (a car file's marker, the fixed-marker file, the calibration file, a ChArUco board)."""
from __future__ import annotations

import cv2

DEFAULT_DICTIONARY = "DICT_4X4_50"  # 50 ids of 4x4 bits: the largest cells, so the smallest readable markers


class UnknownDictionaryError(ValueError):
    """A dictionary name OpenCV does not predefine."""


def dictionary_id(name: str, field_name: str = "dictionary") -> int:
    """OpenCV's constant for a predefined dictionary name; the error names ``field_name``."""
    value = getattr(cv2.aruco, name, None) if isinstance(name, str) else None
    if not isinstance(name, str) or not name.startswith("DICT_") or not isinstance(value, int):
        raise UnknownDictionaryError(f"{field_name}: unknown ArUco dictionary {name!r} (an OpenCV name such as "
                                     f"{DEFAULT_DICTIONARY!r} or 'DICT_6X6_250')")
    return value


def dictionary_size(name: str, field_name: str = "dictionary") -> int:
    """Number of marker ids in the dictionary (ids 0 .. size - 1)."""
    return int(cv2.aruco.getPredefinedDictionary(dictionary_id(name, field_name)).bytesList.shape[0])
