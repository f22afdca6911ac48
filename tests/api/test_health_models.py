"""GET /health, the model endpoints and /simulate, in JSON and MessagePack, over a real server."""

from __future__ import annotations

import numpy as np
import pytest

from service import __version__
from service.api.schemas.health import Health
from service.api.schemas.models import MeshOut, ModelSummary, SimulateOut
from service.registration.confidence import estimator_for

from .conftest import MAX_POINTS, MSGPACK, mp, packed, unpack


def test_health(http, live):
    r = http.get("/health")
    assert r.status_code == 200
    assert r.headers["x-elastreg-instance"] == "alpha"
    body = Health.model_validate(r.json())
    assert body.status == "ok" and body.models == 1 and body.device == "cpu" and body.version == __version__
    assert body.limits.max_points == MAX_POINTS and body.limits.max_sessions == 24
    assert body.instance == "alpha" and body.skipped_models == {}


def test_health_in_msgpack_when_accepted(http):
    r = http.get("/health", headers={"accept": "application/msgpack"})
    assert r.headers["content-type"] == "application/msgpack"
    assert unpack(r.content)["status"] == "ok"


def test_models_and_summary(http):
    models = http.get("/models").json()
    assert [m["id"] for m in models] == ["bar"]
    one = ModelSummary.model_validate(http.get("/models/bar").json())
    assert (one.n_nodes, one.methods) == (81, ["network", "fem"])
    assert one.material.law == "neo-hookean" and one.material.E == 4500.0
    assert "validation" in one.training


@pytest.mark.parametrize("path", ["/models/nope", "/models/nope/mesh"])
def test_unknown_model_is_404(http, path):
    r = http.get(path)
    assert r.status_code == 404 and "nope" in r.json()["detail"] and "bar" in r.json()["detail"]
    r = http.get(path, headers={"accept": "application/msgpack"})
    assert r.status_code == 404 and "nope" in unpack(r.content)["detail"]


def test_mesh_json_and_msgpack_agree(http, entry):
    j = http.get("/models/bar/mesh").json()
    MeshOut.model_validate(j)
    m = unpack(http.get("/models/bar/mesh", headers=MSGPACK).content)
    mesh = entry.mesh
    for key, ref in [
        ("nodes", mesh.nodes),
        ("tets", mesh.tets),
        ("surface_faces", mesh.surface_faces),
        ("surface_nodes", mesh.surface_nodes),
        ("fixed_nodes", mesh.fixed),
        ("region_nodes", entry.region),
    ]:
        np.testing.assert_array_equal(np.asarray(j[key]), ref)
        np.testing.assert_array_equal(m[key], ref)
    assert m["nodes"].dtype == np.float64 and m["tets"].dtype == np.int64


def test_simulate_network_matches_in_process(http, entry, support):
    g = np.tile([0.0, 0.0, 10.0 / support.size], (support.size, 1))
    want = entry.network.predict(g[None], support)[0]
    r = http.post("/models/bar/simulate", json={"forces": {"nodes": support.tolist(), "values": g.tolist()}})
    assert r.status_code == 200
    body = SimulateOut.model_validate(r.json())
    np.testing.assert_allclose(np.asarray(body.displacement), want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(body.net_force, g.sum(0))
    assert body.converged and {"solve", "decode", "encode"} <= set(body.timing_ms)
    assert body.error_estimate == pytest.approx(estimator_for(entry.network).forward_error(want, g, support))
    r = http.post(
        "/models/bar/simulate",
        headers=MSGPACK,
        content=mp({"forces": {"nodes": packed(support, "<i8"), "values": packed(g, "<f8")}}),
    )
    np.testing.assert_allclose(unpack(r.content)["displacement"], want, rtol=1e-12, atol=1e-15)


def _network(http, support, total, **extra):
    g = np.tile([0.0, 0.0, total / support.size], (support.size, 1))
    r = http.post("/models/bar/simulate", json={"forces": {"nodes": support.tolist(), "values": g.tolist()}, **extra})
    assert r.status_code == 200, r.text
    return r.json()


def test_simulate_network_is_not_converged_far_outside_what_it_learnt(http, entry, support):
    """A 1e30 N load: the network's field is 1e29 m and folds elements, its residual infinite."""
    body = _network(http, support, 1e30)
    assert not body["converged"] and body["status"] == "non_finite" and body["error_estimate"] is None
    # past the largest load it was trained on: an answer with its estimate, not converged
    max_force = entry.network.max_force
    past = _network(http, support, 1.5 * max_force)
    assert not past["converged"] and past["status"] == "beyond_training" and past["error_estimate"] > 0
    # the same load on an organ twice as stiff is 0.75 max_force to the network: within its range
    stiff = _network(http, support, 1.5 * max_force, E=2 * entry.network.E0)
    assert stiff["converged"] and stiff["status"] == "converged"
    u = np.asarray(stiff["displacement"])
    g = np.tile([0.0, 0.0, 1.5 * max_force / support.size], (support.size, 1))
    at_E = entry.network.with_stiffness(2 * entry.network.E0)  # the estimate at the body's own E
    assert stiff["error_estimate"] == pytest.approx(estimator_for(at_E).forward_error(u, g, support), rel=1e-3)


def test_a_load_at_the_trained_maximum_is_within_training_whatever_its_rounding(entry, support):
    """The sum of nodal magnitudes rounds: 1 N on 20 phantom nodes summed to 1 + 2e-16, and a
    float32 body (MessagePack's packed arrays) to 1 + 1.5e-8, and was beyond_training. A load
    past max_force by more than rounding still is."""
    from service.api.work import judge_network
    from service.registration.confidence import LOAD_ROUNDING

    net, k = entry.network, support.size
    for share in (1 + 1e-9, 1 + LOAD_ROUNDING / 2):
        g = np.tile([0.0, 0.0, share * net.max_force / k], (k, 1))
        u = net.predict(g[None], support)[0]
        assert judge_network(net, u, g, support)["status"] == "converged", share
    g = np.tile([0.0, 0.0, 1.001 * net.max_force / k], (k, 1))
    assert judge_network(net, net.predict(g[None], support)[0], g, support)["status"] == "beyond_training"


def test_simulate_fem_and_stiffness(http, entry, support):
    g = np.tile([0.0, 0.0, 10.0 / support.size], (support.size, 1))
    r = http.post(
        "/models/bar/simulate", json={"method": "fem", "forces": {"nodes": support.tolist(), "values": g.tolist()}}
    )
    body = r.json()
    assert r.status_code == 200 and body["converged"] and body["method"] == "fem" and body["iterations"] >= 1
    u = np.asarray(body["displacement"])
    np.testing.assert_allclose(u, entry.fem.solve(g, support).u, rtol=1e-8, atol=1e-12)
    stiff = http.post(
        "/models/bar/simulate",
        json={"method": "fem", "E": 9000.0, "forces": {"nodes": support.tolist(), "values": g.tolist()}},
    ).json()
    assert np.abs(stiff["displacement"]).max() < np.abs(u).max()


def test_simulate_an_absurd_fem_load_answers_at_once(http, support):
    """Not a solver thread held for ever: a result that says it did not converge, and why."""
    g = np.tile([0.0, 0.0, 1e12], (support.size, 1))
    r = http.post(
        "/models/bar/simulate", json={"method": "fem", "forces": {"nodes": support.tolist(), "values": g.tolist()}}
    )
    body = r.json()
    assert r.status_code == 200 and not body["converged"] and body["status"] == "load_step_too_small"
    assert http.get("/health").json()["solves"]["running"] == 0


def _measured_residual(entry, nodes, values, u) -> float:
    """u's relative residual under the forces, over the free dofs: ||f_int(u) - g|| / ||g||."""
    asm = entry.fem.assembler
    g = np.zeros((entry.mesh.n_nodes, 3))
    np.add.at(g, nodes, values)
    target = asm.pack(g)
    return float(np.linalg.norm(asm.pack(asm.internal_force(u)) - target) / np.linalg.norm(target))


def _crushing(entry):
    """3 kN pushing the free end's corner back along the bar: Newton runs out of iterations
    part-way along the load (its last residual, of a partial step, was 0.036; the field's 0.93)."""
    corner = int(np.argmin(np.linalg.norm(entry.mesh.nodes - [4.0, 1.0, 1.0], axis=1)))
    return [corner], [[-3000.0, 0.0, 0.0]]


@pytest.mark.parametrize(
    "load, status",
    [
        (lambda entry, support: (support, np.tile([10.0 / support.size], (support.size, 3))), "converged"),
        (lambda entry, support: (support, np.tile([0.0, 0.0, 1e12], (support.size, 1))), "load_step_too_small"),
        (lambda entry, support: _crushing(entry), "max_iter"),
    ],
    ids=["converged", "absurd", "crushing"],
)
def test_simulate_fem_residual_is_the_returned_fields_under_the_body_forces(http, entry, support, load, status):
    """Not the last partial load step's, nor 0.0 where Newton stopped before any iteration: an
    absurd load's answer is the rest state, whose residual is the whole load (1)."""
    nodes, values = load(entry, support)
    body = {"method": "fem", "forces": {"nodes": np.asarray(nodes).tolist(), "values": np.asarray(values).tolist()}}
    r = http.post("/models/bar/simulate", json=body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["status"] == status and out["converged"] == (status == "converged")
    u = np.asarray(out["displacement"])
    want = _measured_residual(entry, nodes, np.asarray(values, float), u)
    if status == "converged":
        assert out["residual"] <= entry.fem.options.rtol and want <= entry.fem.options.rtol
    else:
        assert out["residual"] == pytest.approx(want, rel=1e-9) and out["residual"] > 1e-3
    if status == "load_step_too_small":
        assert not np.any(u) and out["residual"] == pytest.approx(1.0)


@pytest.mark.parametrize(
    "forces, words",
    [
        ({"nodes": [0], "values": [[0, 0, 1]]}, "fixed"),
        ({"nodes": [10_000], "values": [[0, 0, 1]]}, "0..80"),
        ({"nodes": [1.5], "values": [[0, 0, 1]]}, "integers"),
        ({"nodes": [-1], "values": [[0, 0, 1]]}, "non-negative"),
        ({"nodes": [], "values": []}, "non-empty"),
        ({"nodes": [70, 71], "values": [[0, 0, 1]]}, "2 nodes but 1 values"),
        ({"nodes": [70], "values": [[0, 0]]}, "(m, 3)"),
        ({"nodes": [70], "values": "x"}, "array"),
    ],
)
def test_simulate_refuses_bad_forces(http, forces, words):
    r = http.post("/models/bar/simulate", json={"forces": forces})
    assert r.status_code == 422, r.text
    assert any(words in e["msg"] for e in r.json()["detail"]), r.json()


def test_simulate_unknown_model_and_method(http):
    assert (
        http.post("/models/nope/simulate", json={"forces": {"nodes": [70], "values": [[0, 0, 1]]}}).status_code == 404
    )
    r = http.post("/models/bar/simulate", json={"method": "magic", "forces": {"nodes": [70], "values": [[0, 0, 1]]}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "method"]


def test_openapi_and_docs(http):
    spec = http.get("/openapi.json").json()
    for path in (
        "/health",
        "/models",
        "/models/{model}",
        "/models/{model}/mesh",
        "/models/{model}/simulate",
        "/sessions",
        "/sessions/{session_id}/frames",
        "/sessions/{session_id}",
    ):
        assert path in spec["paths"]
    body = spec["paths"]["/sessions/{session_id}/frames"]["post"]["requestBody"]["content"]
    assert set(body) == {"application/json", "application/msgpack"}
    assert {"SessionCreate", "FrameIn", "SimulateIn", "FrameResult"} <= set(spec["components"]["schemas"])
    busy = [op["responses"]["503"] for ops in spec["paths"].values() for op in ops.values() if "503" in op["responses"]]
    assert len(busy) >= 5 and all("Retry-After" in r["headers"] for r in busy)  # every 503 says when to retry
    assert http.get("/docs").status_code == 200


def test_a_bad_store_entry_is_skipped_and_reported(bar_store, tmp_path, caplog):
    """A store with one good entry and two bad ones: the server starts, serves the good one,
    logs the bad ones and names them, with the reason, in /health."""
    import shutil

    import httpx

    from .conftest import start

    store = tmp_path / "store"
    shutil.copytree(bar_store[0] / "bar", store / "bar")
    shutil.copytree(bar_store[0] / "bar", store / "corrupt")
    (store / "corrupt" / "weights.safetensors").write_bytes(b"not the weights")
    (store / "empty").mkdir()
    with caplog.at_level("ERROR", logger="service.store"):
        server = start(store, instance_id="gamma")
    try:
        health = httpx.get(server.url + "/health").json()
        assert health["models"] == 1 and set(health["skipped_models"]) == {"corrupt", "empty"}
        assert "checksum" in health["skipped_models"]["corrupt"]
        assert [m["id"] for m in httpx.get(server.url + "/models").json()] == ["bar"]
        assert "corrupt" in caplog.text
    finally:
        server.stop()


def test_a_started_server_has_made_each_models_estimator(bar_store):
    """Startup makes what a session's first frame would otherwise wait for: every loaded model's
    error estimator (its rest stiffness factorised), for both forward models."""
    from service.registration.confidence import _CACHE_KEY, estimator_for

    from .conftest import start

    server = start(bar_store[0], instance_id="warm")
    try:
        entry = server.app.state.models["bar"]
        for model in (entry.network, entry.fem):
            made = model.__dict__.get(_CACHE_KEY)
            assert made is not None  # no frame has run on this server
            assert estimator_for(model) is made  # the first frame finds it
    finally:
        server.stop()
