"""Exceptions raised by knotlab's core, one per kind of bad input or failed computation."""

from __future__ import annotations


class KnotlabError(Exception):
    """Base class of every error knotlab raises on purpose."""


class InvalidInputError(KnotlabError, ValueError):
    """An argument (array, record, file) does not have the shape, type or values expected."""


class CorruptFileError(KnotlabError):
    """A file knotlab wrote cannot be read back: truncated, wrong version, or failed validation."""


class SolverError(KnotlabError):
    """A numerical solve (QP, linear system) failed or produced non-finite values."""
