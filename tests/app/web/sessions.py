"""Helpers of the labelling-session tests."""

from __future__ import annotations

from knotlab.app.web.session import LabelSession


def accept_something(s: LabelSession) -> str:
    """Try candidates in rank order until one executes; accept it; its demo key."""
    while True:
        result = s.try_selected()
        if result.acceptable:
            s.accept()
            return result.demo_key
        s.reject()
