"""Load test of `knotlab serve`: concurrent clients on loopback, latency, throughput, errors.

Starts `knotlab serve --port 0 --workers W` (or uses --url), then:
  in-process  `Agent.rank` in this process (one BLAS thread) on the same clouds: the baseline;
  1 client    /v1/rank one request at a time: the service's own overhead over the baseline;
  N clients   N threads, each its own HTTP connection, for --seconds: requests/s, p50/p95.
Every request carries a fresh cloud (a test rope's cloud with seeded millimetre jitter, so no
answer comes from a cache) and a request id; a response is *crossed* when its request id, cloud
digest or best demo is not the one computed in-process for that cloud. Errors are non-2xx
answers or failed connections. Test ropes are only observed, never tuned on.

Usage: .venv/bin/python bench/serve_load.py [--clients 4] [--seconds 20] [--workers 2]
       [--top-k 5] [--seed 0] [--url http://127.0.0.1:8090] [--json]
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import httpx  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from knotlab.core.agent import Agent  # noqa: E402
from knotlab.core.arrays import cloud_digest  # noqa: E402
from knotlab.core.machine import machine_info, machine_line  # noqa: E402
from knotlab.core.tasks import get_task  # noqa: E402
from knotlab.core.world.sim import RopeWorld  # noqa: E402
from tests.service.conftest import start_service, stop_service  # noqa: E402

JITTER_M = 0.001


def _clouds(agent: Agent, n: int, seed: int) -> list[np.ndarray]:
    """``n`` distinct clouds: test ropes observed, each with seeded 1 mm jitter."""
    starts = list(get_task(agent.task.name).files.load_task_set("main", "test"))
    rng = np.random.default_rng(seed)
    out = []
    with RopeWorld() as world:
        for i in range(n):
            world.reset(starts[i % len(starts)].start_nodes_k3)
            cloud = agent.observe(world)
            out.append(cloud + rng.normal(0.0, JITTER_M, cloud.shape))
    return out


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> int:
    """Run the three phases and print the table (or JSON)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--top-k", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--baseline", type=int, default=20, help="in-process and 1-client requests")
    ap.add_argument("--url", default=None, help="a running service (default: start one)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    print(f"machine: {machine_line()}")  # every figure names its CPU kind

    agent = Agent.default("greedy")
    pool_n = args.baseline + 400
    clouds = _clouds(agent, pool_n, args.seed)
    expected: dict[int, str] = {}

    # in-process baseline (warm: the first call compiled nothing new, Agent warms at build)
    local = []
    for i in range(args.baseline):
        t0 = time.perf_counter()
        ranked = agent.rank(clouds[i], args.top_k)
        local.append(time.perf_counter() - t0)
        expected[i] = ranked[0].demo_key

    served = None if args.url else start_service("--workers", str(args.workers))
    url = args.url or (served.url if served is not None else "")
    try:
        one = []
        with httpx.Client(timeout=60) as http:
            for i in range(args.baseline):
                body = {"cloud": clouds[i].tolist(), "top_k": args.top_k, "request_id": str(i)}
                t0 = time.perf_counter()
                r = http.post(f"{url}/rank", json=body)
                one.append(time.perf_counter() - t0)
                assert r.status_code == 200, r.text
                assert r.json()["candidates"][0]["demo"] == expected[i]

        lock = threading.Lock()
        next_i = [args.baseline]
        lat: list[float] = []
        errors = crossed = 0
        stop_at = time.monotonic() + args.seconds

        def client() -> None:
            nonlocal errors, crossed
            with httpx.Client(timeout=60) as http:
                while time.monotonic() < stop_at:
                    with lock:
                        i = next_i[0] % pool_n
                        next_i[0] += 1
                    body = {"cloud": clouds[i].tolist(), "top_k": args.top_k, "request_id": str(i)}
                    t0 = time.perf_counter()
                    try:
                        r = http.post(f"{url}/rank", json=body)
                    except httpx.HTTPError:
                        with lock:
                            errors += 1
                        continue
                    dt = time.perf_counter() - t0
                    ok = r.status_code == 200
                    data = r.json() if ok else {}
                    good = ok and (
                        data["request_id"] == str(i)
                        and data["cloud_digest"] == cloud_digest(clouds[i])
                    )
                    with lock:
                        lat.append(dt)
                        errors += not ok
                        crossed += ok and not good
                        if ok and i not in expected:
                            expected[i] = data["candidates"][0]["demo"]

        threads = [threading.Thread(target=client) for _ in range(args.clients)]
        t_start = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t_start
        # the best demo of every cloud answered under load, checked in-process afterwards
        mismatched = sum(
            agent.rank(clouds[i], 1, transfer=False)[0].demo_key != demo
            for i, demo in list(expected.items())[args.baseline : args.baseline + 40]
        )
    finally:
        if served is not None:
            stop_service(served)

    row = {
        "machine": machine_info(),
        "top_k": args.top_k,
        "workers": args.workers,
        "in_process_p50_s": statistics.median(local),
        "one_client_p50_s": statistics.median(one),
        "one_client_ratio": statistics.median(one) / statistics.median(local),
        "clients": args.clients,
        "requests": len(lat),
        "requests_per_s": len(lat) / wall,
        "p50_s": _pct(lat, 50),
        "p95_s": _pct(lat, 95),
        "errors": errors,
        "crossed": crossed + mismatched,
    }
    if args.json:
        print(json.dumps(row, sort_keys=True))
        return 0
    cpu = row["machine"]
    simd = "AVX-512" if "avx512f" in Path("/proc/cpuinfo").read_text() else "no AVX-512"
    print(
        f"# knotlab serve load test; {cpu['cpu_model']} ({simd}), {cpu['usable_cores']} cores, "
        f"load {cpu['load_average_1m']} at the end"
    )
    print("| measure | value |\n|---|---|")
    print(
        f"| in-process Agent.rank p50 (top {args.top_k}, with transfer) | "
        f"{1000 * row['in_process_p50_s']:.0f} ms |"
    )
    print(
        f"| /v1/rank p50, 1 client | {1000 * row['one_client_p50_s']:.0f} ms "
        f"({row['one_client_ratio']:.2f}x in-process; target <= 1.5x) |"
    )
    print(
        f"| {args.clients} clients, {args.seconds:.0f} s, {args.workers} workers | "
        f"{row['requests']} requests, {row['requests_per_s']:.1f} req/s |"
    )
    print(
        f"| /v1/rank p50 / p95 under load | {1000 * row['p50_s']:.0f} / "
        f"{1000 * row['p95_s']:.0f} ms (target p95 < 500 ms) |"
    )
    print(f"| errors / crossed responses | {row['errors']} / {row['crossed']} |")
    return 0 if row["errors"] == 0 and row["crossed"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
