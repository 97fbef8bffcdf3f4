"""viser's per-handle type hints, looked up once per props class instead of once per handle.

viser 1.1 evaluates `typing.get_type_hints` on a handle's props class the first time any of its
properties is set, for every new handle (a `cached_property` of the instance): ~0.3 ms a handle
on a 2-core AVX2 EPYC, and a new labelling state creates some 40-60 scene nodes and GUI handles.
A py-spy sample of the app while four labellers worked had 12 % of the time its threads held the
GIL in those calls. The hints are a function of the class alone (viser's own GUI code caches them
per class too), so they are cached per class here; the mapping handed out is read-only.
"""

from __future__ import annotations

import functools
import logging
import types
import typing
from collections.abc import Mapping
from typing import Any

log = logging.getLogger(__name__)

_MARK = "_knotlab_per_class"


_HINTS: dict[type, Mapping[str, Any]] = {}  # props class -> its hints (a cache)


def _hints_of(props_class: type) -> Mapping[str, Any]:
    hints = _HINTS.get(props_class)
    if hints is None:  # two threads may both compute it: the same value either way
        hints = _HINTS.setdefault(
            props_class, types.MappingProxyType(typing.get_type_hints(props_class))
        )
    return hints


def _prop_hints(self: Any) -> Mapping[str, Any]:
    return _hints_of(type(self._impl.props))


setattr(_prop_hints, _MARK, True)


def cache_prop_hints_per_class() -> bool:
    """Make viser's handles share their props class's type hints; True once installed.

    A viser whose handles do not look their hints up this way is left as it is (False)."""
    try:
        from viser._assignable_props_api import AssignablePropsBase
    except ImportError:  # pragma: no cover - another viser layout
        log.info("viser has no AssignablePropsBase: type hints left per handle")
        return False
    current = AssignablePropsBase.__dict__.get("_prop_hints")
    if not isinstance(current, functools.cached_property):
        log.info("viser's _prop_hints is not a cached property: left as it is")
        return False
    if getattr(current.func, _MARK, False):
        return True
    replacement = functools.cached_property(_prop_hints)
    replacement.__set_name__(AssignablePropsBase, "_prop_hints")
    AssignablePropsBase._prop_hints = replacement  # type: ignore[method-assign, assignment]
    return True
