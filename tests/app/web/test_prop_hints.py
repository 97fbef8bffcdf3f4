"""viser's handles share their props class's type hints once the app's server is built."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys

import numpy as np
import pytest
import viser

from knotlab.app.web.prop_hints import cache_prop_hints_per_class


@pytest.fixture
def server():
    with contextlib.redirect_stdout(io.StringIO()):
        s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


def test_handles_of_one_class_share_read_only_hints_and_still_cast_their_props(server) -> None:
    assert cache_prop_hints_per_class() and cache_prop_hints_per_class()  # idempotent
    a = server.scene.add_frame("/a", show_axes=False)
    b = server.scene.add_frame("/b", show_axes=True)
    sphere = server.scene.add_icosphere("/s", radius=0.1, color=(255, 0, 0))
    # one lookup per class, not per handle (viser's default evaluated them for every handle)
    assert a._prop_hints is b._prop_hints
    assert a._prop_hints is not sphere._prop_hints and "radius" in sphere._prop_hints
    with pytest.raises(TypeError):
        a._prop_hints["position"] = int  # shared, so never writable
    # setting props still goes through viser's casting by those hints
    b.position = (1, 2, 3)
    assert isinstance(b.position, np.ndarray) and np.allclose(b.position, (1.0, 2.0, 3.0))
    sphere.radius = 0.25
    assert sphere.radius == 0.25 and not a.show_axes and b.show_axes


def test_the_apps_server_installs_it_in_a_fresh_process(tmp_path, project_root) -> None:
    # A process of its own: the test above has installed it in this one already.
    script = f"""
from viser._assignable_props_api import AssignablePropsBase as A
def marked():
    return getattr(A.__dict__["_prop_hints"].func, "_knotlab_per_class", False)
assert not marked()
from tests.browser.conftest import start_app
app = start_app("sqlite:///{tmp_path / "k.db"}")
try:
    print("installed" if marked() else "missing")
finally:
    app.stop()
"""
    out = subprocess.run(
        [sys.executable, "-c", script],
        cwd=project_root,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "installed"
