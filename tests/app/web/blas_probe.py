"""Run as a script: build the app as tests and benches do (no command line, no BLAS variables in
the environment) and print, as JSON, the BLAS thread counts of the app's process and of one of
its simulation workers."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path


def blas_threads() -> list[int]:
    """The thread count of every BLAS library loaded in this process."""
    from threadpoolctl import threadpool_info

    return [int(pool["num_threads"]) for pool in threadpool_info() if pool["user_api"] == "blas"]


def main() -> None:
    """Build the app, ask it and a worker, stop it."""
    from tests.browser.conftest import start_app

    with tempfile.TemporaryDirectory() as tmp:
        app = start_app(f"sqlite:///{Path(tmp) / 'blas.db'}")
        try:
            assert app.sim_pool is not None
            worker = app.sim_pool.submit(blas_threads).result(timeout=120)
            print(json.dumps({"app": blas_threads(), "worker": worker}))
        finally:
            app.stop()


if __name__ == "__main__":
    main()
