"""No labelling hotkey is a key viser's camera moves on (pressing it would also move the view)."""

from __future__ import annotations

import re
from pathlib import Path

import viser

from knotlab.app.web.panels import HOTKEYS, MAX_LISTED


def _viser_camera_keys() -> set[str]:
    """The letters and arrows viser's client moves the camera on, read from its own source."""
    source = Path(viser.__file__).parent / "client" / "src" / "CameraControls.tsx"
    block = re.search(r"CAMERA_MOVEMENT_KEYS = new Set\(\[(.*?)\]\)", source.read_text(), re.S)
    assert block is not None, "viser's camera keys were not found in its client source"
    codes = re.findall(r'"(\w+)"', block.group(1))
    return {c.removeprefix("Key").upper() for c in codes}


def test_no_hotkey_moves_the_camera_and_each_is_used_once() -> None:
    camera = _viser_camera_keys()
    assert {"W", "A", "S", "D"} <= camera  # the read found the set
    keys = [key.upper() for _, key in HOTKEYS] + [str(r) for r in range(1, MAX_LISTED + 1)]
    assert not camera & set(keys)
    assert len(keys) == len(set(keys))
