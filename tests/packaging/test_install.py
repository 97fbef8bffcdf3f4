"""A non-editable install works away from the checkout: `pip install .` into a fresh venv.

The wheel is built from a copy of exactly what pyproject.toml names (its readme, license files and
package folders), with this venv's setuptools and no network (``--no-build-isolation``), then
installed with ``--no-deps`` into a venv made here. The third-party dependencies come from this
venv through a ``.pth`` file that names its site-packages folder: a path line adds the folder to
``sys.path`` but runs none of the ``.pth`` files in it, so the editable install's import hook stays
behind. The installed ``knotlab`` must then tie a knot and find its shipped data inside the fresh
venv's site-packages, from a working directory outside the checkout.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow

CHECK_INSTALLED = """
import importlib.metadata, importlib.resources, pathlib, sys
import knotlab
from knotlab.app import defaults
site = pathlib.Path(sys.argv[1]).resolve()
where = pathlib.Path(knotlab.__file__).resolve()
assert where.is_relative_to(site), f"knotlab imported from {where}, not {site}"
assert not any("editable" in type(f).__name__.lower() or "editable" in repr(f).lower()
               for f in sys.meta_path), sys.meta_path
assert importlib.metadata.version("knotlab") == knotlab.__version__ == sys.argv[2]
data = importlib.resources.files("knotlab.core.tasks.overhand").joinpath("data")
names = sorted(p.name for p in data.iterdir() if p.name.endswith(".npz"))
assert len(names) >= 6, names
for path in (defaults.library_path(), defaults.model_path(),
             *(defaults.task_set_path(level, split)
               for level in defaults.LEVELS for split in ("train", "test"))):
    path = pathlib.Path(path).resolve()
    assert path.is_file() and path.is_relative_to(site), path
assert (site / f"knotlab-{knotlab.__version__}.dist-info" / "licenses" / "LICENSE").is_file()
print("ok", where)
"""


def _run(cmd: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{cmd} exited {done.returncode}\n{done.stdout}\n{done.stderr}"
    return done


def _copy_sources(dest: Path) -> Path:
    """What the build reads, per pyproject.toml: the project file, readme, license files and
    the package folders (without byte code)."""
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    dest.mkdir()
    names = ["pyproject.toml", meta["project"]["readme"], *meta["project"]["license-files"]]
    for name in names:
        shutil.copy2(ROOT / name, dest / name)
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    for folder in sorted(set(meta["tool"]["setuptools"]["package-dir"].values())):
        shutil.copytree(ROOT / folder, dest / folder, ignore=skip)
    return dest


def test_a_wheel_installed_in_a_fresh_venv_ties_a_knot_outside_the_checkout(
    tmp_path: Path,
) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PYTHONNOUSERSITE"] = "1"
    src = _copy_sources(tmp_path / "src")
    dist = tmp_path / "dist"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    offline = ["-q", "--no-deps", "--no-index"]
    _run(
        [*pip, "wheel", *offline, "--no-build-isolation", "-w", str(dist), str(src)], tmp_path, env
    )
    (wheel,) = dist.glob("knotlab-*.whl")

    venv = tmp_path / "v"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path, env)
    python = venv / "bin" / "python"
    site = Path(
        _run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            tmp_path,
            env,
        ).stdout.strip()
    )
    # This venv's third-party packages, by plain path lines (no import hooks run from here).
    dep_dirs = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))
    (site / "_knotlab_test_deps.pth").write_text("".join(f"{d}\n" for d in dep_dirs))
    _run([*pip, "--python", str(python), "install", *offline, str(wheel)], tmp_path, env)

    work = tmp_path / "work"
    work.mkdir()
    knotlab = str(venv / "bin" / "knotlab")
    _run([knotlab, "tie", "--out", "x.png"], work, env)
    assert (work / "x.png").stat().st_size > 0
    assert "knotlab app" in _run([knotlab, "app", "--help"], work, env).stdout
    version = _run([knotlab, "--version"], work, env).stdout.split()[-1]
    _run([str(python), "-c", CHECK_INSTALLED, str(site), version], work, env)
