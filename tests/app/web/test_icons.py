"""The app's icons are read ahead into viser's cache, and the list of them is complete."""

from __future__ import annotations

import re
from pathlib import Path

from viser._icons import svg_from_icon

from knotlab.app.web.icons import APP_ICONS, warm_icon_cache

APP = Path(__file__).resolve().parents[3] / "app"


def test_every_icon_the_app_uses_is_read_ahead() -> None:
    used = set()
    for path in APP.rglob("*.py"):
        used |= set(re.findall(r"\b[iI]con\.([A-Z][A-Z0-9_]*)\b", path.read_text()))
    names = {str(icon) for icon in APP_ICONS}
    missing = {u for u in used if u.lower().replace("_", "-") not in names}
    assert used and not missing, f"icons used but not in APP_ICONS: {sorted(missing)}"


def test_read_ahead_icons_are_served_from_the_cache() -> None:
    assert svg_from_icon.cache_parameters()["maxsize"] >= len(APP_ICONS)  # none evicted
    warm_icon_cache()
    before = svg_from_icon.cache_info()
    for icon in APP_ICONS:
        assert svg_from_icon(icon).lstrip().startswith("<svg")
    after = svg_from_icon.cache_info()
    assert after.hits - before.hits == len(APP_ICONS) and after.misses == before.misses
