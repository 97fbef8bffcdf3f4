"""Exceptions raised by knotlab's core, one per kind of bad input or failed computation.

Each class says how the command line ends when it escapes a command (``exit_code``): 2 when the
input was at fault (fix the arguments or files and rerun), 1 when a run on good input failed.
"""

from __future__ import annotations

from enum import Enum
from typing import ClassVar, TypeVar

E = TypeVar("E", bound=Enum)  # a vocabulary (`parse_choice`)


class KnotlabError(Exception):
    """Base class of every error knotlab raises on purpose."""

    exit_code: ClassVar[int] = 2  # most are about an input: the user can fix it


class InvalidInputError(KnotlabError, ValueError):
    """An argument (array, record, file) does not have the shape, type or values expected."""


class OutputPathError(InvalidInputError):
    """An output path cannot be written: a folder, under a file, read-only, wrong extension."""


class CorruptFileError(KnotlabError):
    """A file knotlab wrote cannot be read back: truncated, wrong version, or failed validation."""


class SolverError(KnotlabError):
    """A numerical solve (QP, linear system) failed or produced non-finite values."""

    exit_code: ClassVar[int] = 1  # the input was accepted; the computation failed


def parse_choice(kind: type[E], value: object, noun: str) -> E:
    """The member of string enum ``kind`` named ``value``; one line naming ``noun`` and the
    choices otherwise (every vocabulary a user types goes through here)."""
    try:
        return kind(value)
    except ValueError:
        choices = ", ".join(str(m.value) for m in kind)
        raise InvalidInputError(f"unknown {noun} {value!r}; expected one of {choices}") from None
