"""The icons the app's panels use, read into viser's icon cache before anyone connects.

viser reads an icon from a zip of ~4,000 icons the first time it is used (~60 ms each on a
2-core AVX2 EPYC, the zip's directory parsed anew every time), so the first tab after a start
paid ~0.8 s for its 14 icons while the labeller waited for the page. Its cache keeps them after.
"""

from __future__ import annotations

import logging
import threading

import viser

log = logging.getLogger(__name__)

APP_ICONS: tuple[str, ...] = (
    viser.Icon.ARROW_BACK_UP,
    viser.Icon.ARROW_RIGHT,
    viser.Icon.BRAIN,
    viser.Icon.CHECK,
    viser.Icon.DOWNLOAD,
    viser.Icon.HAND_CLICK,
    viser.Icon.MOVIE,
    viser.Icon.PLAYER_PLAY,
    viser.Icon.PLAYER_STOP,
    viser.Icon.REFRESH,
    viser.Icon.SEARCH,
    viser.Icon.SKULL,
    viser.Icon.X,
    viser.Icon.ZOOM_QUESTION,
)


def warm_icon_cache() -> None:
    """Read every icon of APP_ICONS into viser's cache (a failure only costs the first tab)."""
    from viser._icons import svg_from_icon  # private: viser has no public call for this

    try:
        for name in APP_ICONS:
            svg_from_icon(name)
    except Exception as exc:  # the app works without it, a first tab only waits longer
        log.info("icons not read ahead: %s", exc)


def warm_icon_cache_in_background() -> threading.Thread:
    """Start `warm_icon_cache` on a daemon thread; the thread."""
    thread = threading.Thread(target=warm_icon_cache, name="icon-cache", daemon=True)
    thread.start()
    return thread
