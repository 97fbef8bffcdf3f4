"""`knotlab serve` driven over real HTTP (httpx) and by `knotlab.client`: the answers are the
in-process Agent's, bad requests get a 4xx naming the field, concurrent requests never cross,
a client drives a simulated episode to the knot `knotlab bench` recorded."""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from knotlab.client import KnotlabClient, ServiceError
from knotlab.core.agent import Agent
from knotlab.core.arrays import cloud_digest
from knotlab.core.tasks import get_task
from knotlab.core.world.observation import ObservationModel, observe
from knotlab.core.world.sim import RopeWorld
from tests.service.conftest import start_service, stop_service

pytestmark = pytest.mark.xdist_group("service")


@pytest.fixture(scope="module")
def agent() -> Agent:
    return Agent.default("greedy")


@pytest.fixture(scope="module")
def clouds(agent: Agent) -> list[np.ndarray]:
    """Distinct test-rope clouds (each a fresh scan: none is a library cloud)."""
    starts = get_task("overhand").files.load_task_set("main", "test")
    out = []
    with RopeWorld() as world:
        for start in list(starts)[:12]:
            world.reset(start.start_nodes_k3)
            out.append(agent.observe(world))
    return out


def test_health_model_and_openapi(service):
    assert httpx.get(f"{service.url}/health").json()["status"] == "ok"
    info = httpx.get(f"{service.url}/model").json()
    assert info["task"] == "overhand" and info["library"]["observation_model"] == "centreline"
    assert info["default_policy"] == "greedy" and info["model"]
    schema = httpx.get(service.url.rsplit("/v1", 1)[0] + "/openapi.json").json()
    assert {"/v1/rank", "/v1/choose", "/v1/health", "/v1/model"} <= set(schema["paths"])


def test_rank_is_the_in_process_agents_ranking(service, agent, clouds):
    cloud = clouds[0]
    with KnotlabClient(service.url.rsplit("/v1", 1)[0]) as kl:
        ranked = kl.rank(cloud, top_k=5)
    with threadpool_limits(1):  # as in the service's workers: one BLAS thread, the same sums
        local = agent.rank(cloud, 5)
    assert [r.demo for r in ranked] == [c.demo_key for c in local]
    for r, c in zip(ranked, local, strict=False):
        # the same computation; the scan's float32 kernels may round differently in another
        # process (vector paths depend on array alignment), so: equal to float32 precision
        assert r.q == pytest.approx(c.q, rel=1e-6)
        assert r.registration_cost == pytest.approx(c.nn_cost, rel=1e-6)
        assert r.trajectory is not None and c.trajectory is not None
        mine = r.trajectory.to_gripper_trajectory()
        assert np.allclose(mine.positions_gt3, c.trajectory.positions_gt3, atol=1e-6)
        assert np.array_equal(mine.closed_gt, c.trajectory.closed_gt)
        grasp = c.trajectory.times_t[
            np.flatnonzero(np.diff(c.trajectory.closed_gt[1].astype(int)) > 0) + 1
        ]
        assert np.allclose(r.trajectory.close_times[1], grasp[: len(r.trajectory.close_times[1])])


BAD = [
    ({"cloud": [[0, 0, 0]] * 5}, 422, "cloud: List should have at least 10 items"),
    ({"cloud": "x"}, 422, "cloud:"),
    ({}, 422, "cloud: Field required"),
    ({"cloud": [[0, 0]] + [[0, 0, 0]] * 20}, 422, "cloud.0:"),
    ({"cloud": [[0, 0, 0]] * 20, "top_k": 0}, 422, "top_k:"),
    ({"cloud": [[0, 0, 0]] * 20, "top_k": 10**6}, 422, "top_k:"),
    ({"cloud": [[0, 0, 0]] * 20, "colour": 1}, 422, "colour: Extra inputs"),
    ({"cloud": [[0, 0, 0]] * 20, "task": "figure8"}, 422, "task: this service decides for"),
]


@pytest.mark.parametrize("body,status,message", BAD)
def test_a_malformed_rank_request_is_answered_4xx_naming_the_field(service, body, status, message):
    r = httpx.post(f"{service.url}/rank", json=body)
    assert r.status_code == status and message in r.json()["error"], r.text


def test_not_json_nan_and_oversized_bodies(service):
    r = httpx.post(
        f"{service.url}/rank", content=b"{nope", headers={"content-type": "application/json"}
    )
    assert r.status_code == 422 and r.json()["error"] == "body: not valid JSON"
    nan = b'{"cloud": [[NaN, 0, 0]' + b", [0, 0, 0]" * 12 + b"]}"
    r = httpx.post(f"{service.url}/rank", content=nan, headers={"content-type": "application/json"})
    assert r.status_code == 422 and "cloud.0.0: Input should be a finite number" in r.text
    huge = {"cloud": [[0.123456789, 0.123456789, 0.123456789]] * 120_000}
    r = httpx.post(f"{service.url}/rank", json=huge)
    assert r.status_code == 413 and "exceeds the limit" in r.json()["error"]


def test_choose_policies_and_what_lookahead_needs(service, agent, clouds):
    cloud = clouds[1]
    with KnotlabClient(service.url.rsplit("/v1", 1)[0]) as kl:
        greedy = kl.choose(cloud)
        assert greedy.policy == "greedy"
        assert greedy.chosen.demo == agent.rank(cloud, 1)[0].demo_key
        nearest = int(np.argmin(agent.scan(cloud).nn_cost_a))  # the lowest registration cost
        assert kl.choose(cloud, policy="nn").chosen.demo == agent.library.keys[nearest]
        with pytest.raises(ServiceError, match="rope_nodes: policy 'la1x2' simulates"):
            kl.choose(cloud, policy="la1x2")
        with pytest.raises(ServiceError, match="policy: unknown policy 'best'"):
            kl.choose(cloud, policy="best")
        with pytest.raises(ServiceError, match="policy: 'ala2x5k4' re-estimates its model"):
            kl.choose(cloud, policy="ala2x5k4")
        with pytest.raises(ServiceError, match="step_index"):
            kl.choose(cloud, step_index=5)


def test_concurrent_requests_never_cross(service, agent, clouds):
    expected = [agent.rank(c, 3, transfer=False) for c in clouds]
    work = [i % len(clouds) for i in range(36)]

    def ask(i: int) -> tuple[int, dict]:
        body = {"cloud": clouds[i].tolist(), "top_k": 3, "request_id": f"r{i}", "transfer": False}
        with httpx.Client(timeout=60) as http:
            return i, http.post(f"{service.url}/rank", json=body).json()

    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(ask, work))
    workers = set()
    for i, ans in answers:
        assert ans["request_id"] == f"r{i}" and ans["cloud_digest"] == cloud_digest(clouds[i])
        assert [c["demo"] for c in ans["candidates"]] == [c.demo_key for c in expected[i]]
        workers.add(ans["worker"])
    assert len(workers) == 2  # both workers answered


def test_a_client_drives_a_simulated_episode_to_the_benchs_knot(service, agent: Agent):
    """Observe in the world, ask the service, execute what it returns, repeat."""
    task = get_task("overhand")
    start = task.files.load_task_set("main", "test")[3]
    # The bench's greedy episode of this start, run here: a results file's episode is another
    # CPU kind's sample once the simulation's last bits differ (docs/determinism.md).
    with RopeWorld() as world:
        record = agent.run_episode(world, start).outcome().to_dict()
    assert agent.model is not None
    chosen, stages, scores, knot = [], [], [], False
    with KnotlabClient(service.url.rsplit("/v1", 1)[0]) as kl, RopeWorld() as world:
        info = kl.model()
        assert info["model"] == agent.model.content_hash()  # the bench's model is the service's
        model = ObservationModel.parse(info["library"]["observation_model"])
        world.reset(start.start_nodes_k3)
        for step in range(task.step_limit):
            choice = kl.choose(observe(world, model), step_index=step)
            assert choice.chosen.trajectory is not None
            world.execute(choice.chosen.trajectory.to_gripper_trajectory())
            reading = task.stage(world.rope_nodes())
            chosen.append(choice.chosen.demo)
            stages.append(reading.stage)
            scores.append(choice.chosen.score)
            if reading.success:
                knot = True
                break
    assert knot == record["success"] is True
    assert chosen == record["chosen"] and stages == record["stages"]
    assert scores == pytest.approx(record["scores"], abs=1e-5)


def test_a_non_loopback_host_needs_the_token_and_ctrl_c_stops_it():
    served = start_service("--workers", "1", "--host", "0.0.0.0", "--model", "none")
    try:
        # the generated token was printed before the URL
        token = re.search(r"generated an access token .*: (\S+)", served.printed)
        assert token is not None, served.printed
        url = re.sub(r"//0\.0\.0\.0", "//127.0.0.1", served.url)
        assert httpx.get(f"{url}/health").status_code == 401
        r = httpx.get(f"{url}/model", headers={"Authorization": "Bearer wrong"})
        assert r.status_code == 401 and "bearer token" in r.json()["error"]
        ok = httpx.get(f"{url}/model", headers={"Authorization": f"Bearer {token.group(1)}"})
        assert ok.status_code == 200 and ok.json()["model"] is None
    finally:
        assert stop_service(served) < 5
