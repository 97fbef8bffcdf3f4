"""pyproject.toml lists every package and data file a wheel needs (a fast check; the slow one,
test_install.py, builds and installs the wheel).

setuptools is given an explicit package list (the folders install under other names, knotlab.*),
so a new sub-package or data file is silently left out of a non-editable install unless it is
added there: these tests catch that without building anything.
"""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

import pytest

import knotlab

ROOT = Path(__file__).resolve().parents[2]
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())
SETUPTOOLS = CONFIG["tool"]["setuptools"]


def _package_folders() -> dict[str, Path]:
    """Every importable package in the mapped folders: its installed name and its folder."""
    found = {}
    for name, folder in SETUPTOOLS["package-dir"].items():
        for init in sorted((ROOT / folder).rglob("__init__.py")):
            rel = init.parent.relative_to(ROOT / folder)
            found[".".join((name, *rel.parts))] = init.parent
    return found


def test_every_package_folder_is_listed() -> None:
    assert len(set(SETUPTOOLS["packages"])) == len(SETUPTOOLS["packages"]), "listed twice"
    listed = set(SETUPTOOLS["packages"])
    folders = _package_folders()
    assert sorted(set(folders) - listed) == [], "add these to [tool.setuptools] packages"
    assert sorted(listed - set(folders)) == [], "listed packages without a folder"


def test_every_data_file_is_package_data() -> None:
    """Files other than Python source inside a package folder match a package-data pattern."""
    patterns = SETUPTOOLS["package-data"]
    folders = _package_folders()
    missing = []
    for name, folder in folders.items():
        for path in folder.rglob("*"):
            if not path.is_file() or path.suffix in (".py", ".pyc") or "__pycache__" in path.parts:
                continue
            owner = max((p for p in folders if path.is_relative_to(folders[p])), key=len)
            rel = path.relative_to(folders[owner]).as_posix()
            if owner == name and not any(fnmatch.fnmatch(rel, g) for g in patterns.get(owner, [])):
                missing.append(f"{owner}: {rel}")
    assert missing == [], "add these to [tool.setuptools.package-data]"


@pytest.mark.parametrize("package", sorted(CONFIG["tool"]["setuptools"]["package-data"]))
def test_package_data_patterns_match_files(package: str) -> None:
    folder = _package_folders()[package]
    for pattern in SETUPTOOLS["package-data"][package]:
        assert list(folder.glob(pattern)), f"{package}: {pattern} matches nothing"


def test_the_version_is_written_once() -> None:
    assert "version" in CONFIG["project"]["dynamic"] and "version" not in CONFIG["project"]
    assert SETUPTOOLS["dynamic"]["version"] == {"attr": "knotlab.__version__"}
    assert knotlab.__version__[:1].isdigit()
