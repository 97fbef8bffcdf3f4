"""The layering contract of docs/architecture.md, checked on the source: imports point down only.

core/ imports neither knotlab.app nor knotlab.labeling_db; labeling_db/ does not import the app;
every package installs under the one distinct name knotlab.*; the command line builds without
importing the simulator (so `knotlab --help` stays fast and prints no PyBullet banner).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> list[str]:
    """Every module name a file imports (absolute imports; relative ones resolved to knotlab.*)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                names.append(f"<relative:{node.module}>")
            elif node.module:
                names.append(node.module)
    return names


def _violations(folder: str, forbidden: tuple[str, ...]) -> list[str]:
    out = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for name in _imports(path):
            if name.startswith(forbidden) or name.split(".")[0] in ("core", "app", "labeling_db"):
                out.append(f"{path.relative_to(ROOT)} imports {name}")
    return out


def test_core_imports_neither_the_app_nor_the_database() -> None:
    assert _violations("core", ("knotlab.app", "knotlab.labeling_db", "<relative")) == []


def test_labeling_db_does_not_import_the_app() -> None:
    assert _violations("labeling_db", ("knotlab.app", "<relative")) == []


def test_app_uses_only_the_installed_names() -> None:
    assert _violations("app", ("<relative",)) == []


@pytest.mark.parametrize(
    "folder, subpackages",
    [
        (
            "core",
            {"world", "registration", "demos", "selection", "execution", "experiments", "tasks"},
        )
    ],
)
def test_core_is_split_by_stage_of_the_science(folder: str, subpackages: set[str]) -> None:
    found = {p.parent.name for p in (ROOT / folder).glob("*/__init__.py")}
    assert subpackages <= found


def test_nothing_installs_as_a_bare_core_or_app() -> None:
    import knotlab.app
    import knotlab.core

    assert Path(knotlab.core.__file__).resolve().parent == ROOT / "core"
    assert Path(knotlab.app.__file__).resolve().parent == ROOT / "app"
    code = "import importlib.util as u; print(u.find_spec('core'), u.find_spec('app'))"
    # From a neutral directory, a bare `core` or `app` must not resolve to this project.
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd="/", check=True
    ).stdout
    assert str(ROOT) not in out


def test_the_command_line_builds_without_the_simulator() -> None:
    code = (
        "import sys; from knotlab.app.cli import build_parser; build_parser(); "
        "print('pybullet' in sys.modules, 'knotlab.core.world.sim' in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.split() == ["False", "False"]
    assert "pybullet build time" not in res.stdout + res.stderr


def test_importing_the_simulator_prints_no_banner() -> None:
    code = "import knotlab.core.world.sim"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout == "" and res.stderr == ""


def test_only_a_tasks_own_folder_names_it() -> None:
    """A task is reached through the Task protocol: the code outside its folder never names it
    (registrations live in the folder; pyproject.toml and docs/ may)."""
    import re

    names = re.compile(r"figure[-_ ]?(8|eight)", re.IGNORECASE)
    found = []
    for top in ("core", "app", "labeling_db", "knotlab"):
        for path in (ROOT / top).rglob("*.py"):
            if path.is_relative_to(ROOT / "core" / "tasks" / "figure8"):
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
                if names.search(line):
                    found.append(f"{path.relative_to(ROOT)}:{n}")
    assert not found, f"the figure-eight task is named outside its folder: {found}"
