"""What the operator's page needs from the service, without a browser: the binary cloud format and its
size bound, the running job's cloud snapshot (written off the control thread), the cloud endpoint on a
running and on an ended job, ``whoami``, the page itself with its Content-Security-Policy, and the part
id's one limit."""

from __future__ import annotations

import base64
import hashlib
import json
import re
import shutil
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from cell.api.app import create_app
from cell.api.routes import docs, page
from cell.jobs import live_cloud
from cell.jobs.live_cloud import LIVE_CLOUD_FILE, LiveCloudWriter, read_live_cloud
from cell.line.config import PART_ID_MAX
from cell.perception.cloud import CloudAccumulator, read_ply, write_ply
from cell.service.clouds import HEADER, JobCloud, decode_cloud, encode_cloud, job_cloud
from cell.service.keys import PERMISSIONS, Role
from cell.service.startup import ServiceSettings
from cell.web import STATIC_DIR

from .conftest import FRANKA, REPO, wait_for
from .test_service_api import _auth, _client, _wait

# ---------------------------------------------------------------------------------------------- format


def test_a_cloud_goes_out_quantized_within_one_step_and_reads_back() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform([0.3, -0.2, 0.0], [0.6, 0.2, 0.25], size=(5000, 3))
    data = encode_cloud(JobCloud(points, final=True))
    magic, n, total, final, *box = struct.unpack_from("<4sIII3f3f", data)
    assert (magic, n, total, final) == (b"CLD1", 5000, 5000, 1) and HEADER.size == 40
    assert len(data) == 40 + 6 * 5000
    lo, hi = np.array(box[:3]), np.array(box[3:])
    assert np.allclose(lo, points.min(axis=0), atol=1e-6) and np.allclose(hi, points.max(axis=0), atol=1e-6)
    decoded, total, final = decode_cloud(data)
    assert total == 5000 and final
    step = (hi - lo) / 65535
    assert np.all(np.abs(decoded - points) <= step / 2 + 1e-7)
    assert encode_cloud(JobCloud(points, final=True)) == data  # deterministic


def test_200k_points_take_at_most_2_mb_and_max_points_subsamples_evenly() -> None:
    points = np.random.default_rng(1).normal(0.4, 0.1, size=(300_000, 3))
    data = encode_cloud(JobCloud(points, final=False))
    assert len(data) == 40 + 6 * 200_000 <= 2_000_000  # the default bound
    decoded, total, final = decode_cloud(data)
    assert decoded.shape == (200_000, 3) and total == 300_000 and not final
    few = decode_cloud(encode_cloud(JobCloud(points, final=False), max_points=3))[0]
    assert np.allclose(few, points[[0, 100_000, 200_000]], atol=2e-5)


def test_an_empty_cloud_and_non_finite_points() -> None:
    assert decode_cloud(encode_cloud(JobCloud(np.zeros((0, 3)), final=False)))[0].shape == (0, 3)
    points = np.array([[0.1, 0.2, 0.3], [np.nan, 0.0, 0.0], [0.2, 0.2, np.inf]])
    decoded, total, _ = decode_cloud(encode_cloud(JobCloud(points, final=True)))
    assert total == 1 and np.allclose(decoded, [[0.1, 0.2, 0.3]], atol=1e-6)
    with pytest.raises(ValueError, match="not a cloud answer"):
        decode_cloud(b"ply\n" + bytes(60))


def test_a_jobs_cloud_is_its_snapshot_while_it_runs_and_cloud_ply_once_it_ended(tmp_path: Path) -> None:
    assert job_cloud(tmp_path).points.shape == (0, 3)
    live = np.array([[0.1, 0.0, 0.0]], dtype=np.float32)
    np.save(tmp_path / LIVE_CLOUD_FILE, live)
    write_ply(tmp_path / "cloud.ply", np.array([[0.2, 0.0, 0.0], [0.3, 0.0, 0.0]]))
    running = job_cloud(tmp_path)  # cloud.ply without result.json: still being written
    assert not running.final and np.allclose(running.points, live)
    (tmp_path / "result.json").write_text("{}")
    ended = job_cloud(tmp_path)
    assert ended.final and ended.points.shape == (2, 3)


def test_a_jobs_cloud_as_it_ends_is_its_cloud_ply_not_none(tmp_path: Path) -> None:
    """An ending job removes its snapshot, writes cloud.ply, and result.json only after its metrics: in
    between, its cloud is cloud.ply, not yet final (it had been no points: the page's 3D view went blank);
    a cloud.ply still being written is not taken for a smaller cloud."""
    write_ply(tmp_path / "cloud.ply", np.array([[0.2, 0.0, 0.0], [0.3, 0.0, 0.0]]))
    ending = job_cloud(tmp_path)
    assert not ending.final and ending.points.shape == (2, 3)
    whole = (tmp_path / "cloud.ply").read_bytes()
    (tmp_path / "cloud.ply").write_bytes(whole[:-24])  # one point short of its header
    assert job_cloud(tmp_path).points.shape == (0, 3)
    with pytest.raises(ValueError, match="not the 2 points of its header"):
        read_ply(tmp_path / "cloud.ply")


# ---------------------------------------------------------------------------------------------- snapshot


def test_the_accumulator_never_changes_a_cloud_it_handed_out() -> None:
    """What lets the control thread hand a reference to the snapshot writer without a copy."""
    rng = np.random.default_rng(2)
    cloud = CloudAccumulator(0.005)
    cloud.add(rng.uniform(0.0, 0.1, size=(2000, 3)))
    handed_out = cloud.points
    kept = handed_out.copy()
    cloud.add(rng.uniform(0.05, 0.15, size=(2000, 3)))  # shares voxels with the first: averaged anew
    assert cloud.points is not handed_out and cloud.points.shape[0] > handed_out.shape[0]
    assert np.array_equal(handed_out, kept)


def test_the_snapshot_is_written_by_a_thread_of_its_own_at_most_once_a_period(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    writers: list[str] = []
    save = np.save

    def recording_save(*args: object, **kwargs: object) -> None:
        writers.append(threading.current_thread().name)
        save(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(live_cloud.np, "save", recording_save)
    path = tmp_path / LIVE_CLOUD_FILE
    writer = LiveCloudWriter(path, log=lambda message: pytest.fail(message), period_s=0.5)
    clouds = [np.full((1000 * (k + 1), 3), float(k)) for k in range(3)]
    started = time.perf_counter()
    for cloud in clouds:
        writer.offer(cloud)
    assert time.perf_counter() - started < 0.05  # the caller (the control thread) never waits for a write

    def newest_written() -> bool:
        snapshot = read_live_cloud(path)
        return snapshot is not None and snapshot.shape[0] == 3000

    assert wait_for(newest_written, timeout_s=5.0)
    assert writers and set(writers) == {"live-cloud"}
    assert writer.n_written <= 2  # the first offer at once, then the newest after the period
    assert not list(tmp_path.glob("*.tmp"))
    writer.close()
    assert not path.exists()


def test_a_snapshot_that_cannot_be_written_is_logged_and_the_job_goes_on(tmp_path: Path) -> None:
    messages: list[str] = []
    writer = LiveCloudWriter(tmp_path / "gone" / LIVE_CLOUD_FILE, log=messages.append, period_s=0.01)
    writer.offer(np.zeros((5, 3)))
    assert wait_for(lambda: bool(messages), timeout_s=5.0)
    assert "not written" in messages[0] and writer.n_written == 0
    writer.close()


# ---------------------------------------------------------------------------------------------- HTTP


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory):
    client, keys = _client(tmp_path_factory.mktemp("web-api"))
    with client:
        yield client, keys


def test_the_page_is_served_with_a_policy_that_runs_only_its_own_scripts(served) -> None:
    client, _ = served
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    policy = page.headers["content-security-policy"]
    import_map = re.search(r'<script type="importmap">(.*?)</script>', page.text, re.DOTALL)
    assert import_map is not None
    digest = base64.b64encode(hashlib.sha256(import_map.group(1).encode()).digest()).decode()
    assert f"script-src 'self' 'sha256-{digest}'" in policy
    assert "'unsafe-inline'" not in policy and "'unsafe-eval'" not in policy
    assert "connect-src 'self'" in policy and "frame-ancestors 'none'" in policy
    assert "https://" not in page.text and "http://" not in page.text
    script = client.get("/static/js/main.js")
    assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    assert script.headers["cache-control"] == "no-cache"
    for target in json.loads(import_map.group(1))["imports"].values():
        if not target.endswith("/"):
            assert client.get(target).status_code == 200, target
    assert client.get("/static/vendor/three/OrbitControls.js").status_code == 200
    assert client.get("/static/../cell.db").status_code == 404
    assert "/" not in client.get("/api/v1/openapi.json").json()["paths"]


def test_the_page_under_static_and_every_static_file_carry_the_pages_policy(served) -> None:
    """``/static/index.html`` is the page itself: it was served with no policy and no ``frame-ancestors``
    (another site could frame it, and nothing kept out a script the policy keeps out at ``/``)."""
    client, _ = served
    policy = client.get("/").headers["content-security-policy"]
    for path in ("/static/index.html", "/static/js/main.js", "/static/favicon.svg", "/static/css/app.css"):
        answer = client.get(path)
        assert answer.status_code == 200, path
        assert answer.headers["content-security-policy"] == policy, path
        assert answer.headers["x-content-type-options"] == "nosniff", path
        assert answer.headers["cache-control"] == "no-cache", path
    etag = client.get("/static/index.html").headers["etag"]
    revalidated = client.get("/static/index.html", headers={"If-None-Match": etag})
    assert revalidated.status_code == 304 and revalidated.headers["content-security-policy"] == policy


def test_a_page_upgraded_in_place_goes_out_with_its_new_policy_at_both_addresses(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``/`` reads the page at each request; ``/static/index.html``'s policy was the hash of the import map
    the service started with, and refused the upgraded page's own import map."""
    static = tmp_path / "static"
    shutil.copytree(STATIC_DIR, static)
    monkeypatch.setattr(page, "STATIC_DIR", static)
    monkeypatch.setattr(page, "INDEX_HTML", static / "index.html")
    app = FastAPI()
    page.add_page(app)
    html = (static / "index.html").read_text()
    upgraded = re.sub(r'(<script type="importmap">)', r'\1{"scopes": {}}', html, count=1)
    assert upgraded != html
    (static / "index.html").write_text(upgraded)
    with TestClient(app) as client:
        policies = {client.get(path).headers["content-security-policy"]
                    for path in ("/", "/static/index.html")}
    assert policies == {page.security_headers(upgraded)["Content-Security-Policy"]}


def test_the_api_docs_and_their_files_carry_a_policy_of_their_own(served) -> None:
    """``/docs`` (Swagger UI) and its files went out with no security header: any site could frame the
    docs page, and nothing kept out a script it did not load itself. Its one inline script, Swagger UI's
    start, is allowed by its hash, and the OAuth2 redirect page (an inline script, no OAuth2 flow) is gone."""
    client, _ = served
    docs = client.get("/docs")
    assert docs.status_code == 200 and docs.headers["content-type"].startswith("text/html")
    policy = docs.headers["content-security-policy"]
    [start] = page.INLINE_SCRIPT.findall(docs.text)
    digest = base64.b64encode(hashlib.sha256(start.encode()).digest()).decode()
    assert f"script-src 'self' 'sha256-{digest}';" in policy and "frame-ancestors 'none'" in policy
    assert "'unsafe-inline'" not in policy and "connect-src 'self'" in policy
    files = re.findall(r'(?:src|href)="(/static-offline-docs/[^"]+)"', docs.text)
    assert len(files) == 3, files
    for path in ("/docs", *files):
        answer = client.get(path)
        assert answer.status_code == 200, path
        assert answer.headers["content-security-policy"] == policy, path
        assert answer.headers["x-content-type-options"] == "nosniff", path
        assert answer.headers["referrer-policy"] == "no-referrer", path
    assert client.head("/docs").headers["content-security-policy"] == policy
    assert client.get("/docs/oauth2-redirect").status_code == 404


def test_the_docs_files_are_only_those_the_docs_page_loads(served) -> None:
    """The service offers Swagger UI alone, but fastapi_offline's copy of ReDoc (1 MB of script no page of
    it loads) was served beside it; it, and any other file not on the docs page, answers 404."""
    client, _ = served
    assert (docs.DOCS_FILES / "redoc.standalone.js").is_file()  # the package still ships it
    for name in ("redoc.standalone.js", "../index.html", ""):
        assert client.get(f"/static-offline-docs/{name}").status_code == 404, name
        assert client.head(f"/static-offline-docs/{name}").status_code == 404, name
    loaded = set(re.findall(r'(?:src|href)="/static-offline-docs/([^"]+)"', client.get("/docs").text))
    assert loaded == docs.DOCS_FILE_NAMES


@pytest.mark.parametrize("path", ["/", "/static/js/main.js", "/healthz"])
def test_head_answers_where_get_does_as_uptime_monitors_ask(served, path: str) -> None:
    """``HEAD /`` answered 405 Method Not Allowed, which an uptime monitor sending HEAD reads as down."""
    client, _ = served
    head, get = client.head(path), client.get(path)
    assert head.status_code == get.status_code == 200 and head.content == b""
    assert head.headers["content-type"] == get.headers["content-type"]
    assert head.headers["content-length"] == get.headers["content-length"]


def test_readyz_answers_head_with_a_key(served) -> None:
    client, keys = served
    head = client.head("/readyz", headers=_auth(keys["viewer"]))
    assert head.status_code == client.get("/readyz", headers=_auth(keys["viewer"])).status_code == 200


def test_every_operation_of_the_api_document_has_its_own_id(served) -> None:
    """A HEAD and a GET of one route had shared an operation id, which generated clients refuse."""
    client, _ = served
    paths = client.get("/api/v1/openapi.json").json()["paths"]
    ids = [op["operationId"] for item in paths.values() for op in item.values() if "operationId" in op]
    assert len(ids) == len(set(ids)) and "readyz_head" in ids


def test_whoami_names_the_key_and_what_its_role_may_do(served) -> None:
    client, keys = served
    for role, key in keys.items():
        who = client.get("/api/v1/whoami", headers=_auth(key)).json()
        assert who == {"name": role, "role": role,
                       "permissions": sorted(p.value for p in PERMISSIONS[Role(role)])}
    assert client.get("/api/v1/whoami", headers=_auth("cell_" + "x" * 43)).status_code == 401
    assert client.get("/api/v1/whoami").status_code == 401


def test_the_cloud_endpoint_serves_a_running_jobs_snapshot_then_its_final_cloud(served) -> None:
    client, keys = served
    viewer, op = _auth(keys["viewer"]), _auth(keys["operator"])
    assert client.get("/api/v1/jobs/0000000000000000/cloud", headers=viewer).status_code == 404
    job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 120}, headers=op).json()
    assert client.get(f"/api/v1/jobs/{job['id']}/cloud", params={"max_points": 0},
                      headers=viewer).status_code == 422

    def live_points() -> int:
        answer = client.get(f"/api/v1/jobs/{job['id']}/cloud", headers=viewer)
        assert answer.status_code == 200 and answer.headers["content-type"] == "application/octet-stream"
        points, _, final = decode_cloud(answer.content)
        assert not final, "a final cloud while the job runs"
        return points.shape[0]

    try:
        assert wait_for(lambda: live_points() > 1000, timeout_s=90.0), "no live cloud while the job ran"
        assert client.get(f"/api/v1/jobs/{job['id']}", headers=viewer).json()["status"] == "running"
    finally:
        client.post(f"/api/v1/jobs/{job['id']}/stop", headers=op)
    ended = _wait(client, keys["viewer"], job["id"], {"stopped", "completed", "failed"})
    answer = client.get(f"/api/v1/jobs/{job['id']}/cloud", params={"max_points": 1000}, headers=viewer)
    points, total, final = decode_cloud(answer.content)
    assert final and total == ended["result"]["n_cloud_points"] > 1000
    assert points.shape == (1000, 3) and len(answer.content) == 40 + 6 * 1000
    listed = {f["name"] for f in client.get(ended["links"]["files"], headers=viewer).json()}
    assert LIVE_CLOUD_FILE not in listed and "cloud.ply" in listed  # the snapshot goes with the job


def test_a_part_id_has_one_limit_for_rest_the_form_opc_ua_and_the_docs(tmp_path: Path) -> None:
    """A job's part id took 128 characters through REST (and the form's field as many), where the README,
    the line's commands and OPC UA say 64."""
    app = create_app(ServiceSettings(config_file=FRANKA, data_dir=tmp_path))
    schema = app.openapi()["components"]["schemas"]
    assert schema["JobSubmit"]["properties"]["part_id"]["anyOf"][0]["maxLength"] == PART_ID_MAX
    assert schema["LineCommandIn"]["properties"]["part_id"]["anyOf"][0]["maxLength"] == PART_ID_MAX
    form = (STATIC_DIR / "js" / "views" / "submit.js").read_text()
    constant = re.search(r"^const PART_ID_MAX = (\d+);$", form, re.MULTILINE)
    assert constant is not None and constant[1] == str(PART_ID_MAX)
    assert 'const part = h("input", { type: "text", maxlength: PART_ID_MAX,' in form
    assert f"**Part ids.** 1 to {PART_ID_MAX} printable ASCII characters" in (REPO / "README.md").read_text()
