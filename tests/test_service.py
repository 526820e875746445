"""The batch service over real HTTP: a real redis-server, the uvicorn app and an RQ worker
in their own processes (service.local.LocalStack), real files on disk.

The tests share one stack and run in file order; the ones that kill workers come last.
"""
from __future__ import annotations

import io
import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import httpx
import pytest
import trimesh

from service.local import LocalStack
from service.storage import zip_tree

from .conftest import REC
from .smplx_synthetic import write_smplx_model

TOKENS = {"alice": "alice-secret-token", "bob": "bob-secret-token-2"}
LIMITS = {"PROX_MAX_UPLOAD_MB": "8", "PROX_MAX_EXTRACTED_MB": "40", "PROX_MAX_FRAMES": "4",
          "PROX_MAX_RECORDINGS": "2", "PROX_JOB_STALE_S": "15", "PROX_REAP_INTERVAL_S": "1"}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    root = tmp_path_factory.mktemp("service")
    tokens = ",".join(f"{name}:{token}" for name, token in TOKENS.items())
    models = write_smplx_model(root / "models", "NEUTRAL").parent  # no male or female file
    with LocalStack(root, tokens, workers=1,
                    env={**LIMITS, "PROX_MODEL_DIR": str(models)}) as running:
        yield running


def client(stack: LocalStack, user: str | None = "alice") -> httpx.Client:
    headers = {"Authorization": f"Bearer {TOKENS[user]}"} if user else {}
    return httpx.Client(base_url=stack.url, headers=headers, timeout=60)


@pytest.fixture(scope="module")
def dataset_zip(sitting_data, tmp_path_factory) -> Path:
    archive = tmp_path_factory.mktemp("upload") / "sitting.zip"
    zip_tree(sitting_data, archive)
    return archive


def submit(http: httpx.Client, archive: Path | bytes, **form: str) -> httpx.Response:
    content = archive if isinstance(archive, bytes) else Path(archive).read_bytes()
    return http.post("/v1/jobs", data=form,
                     files={"file": ("upload.zip", content, "application/zip")})


def wait(http: httpx.Client, job_id: str, until, timeout: float = 300) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        answer = http.get(f"/v1/jobs/{job_id}")
        job = answer.json()
        if answer.status_code != 503 and until(job):  # 503: Redis down, ask again
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} never reached the state; last: {job}")


def ended(job: dict) -> bool:
    return job["status"] in ("finished", "failed", "cancelled")


def running(job: dict) -> bool:
    return job["status"] == "running" and job["progress"]["stage"] not in (None, "preparing")


def edited_zip(source: Path, drop: str | None = None,
               replace: dict[str, bytes] | None = None) -> bytes:
    """A copy of ``source`` without ``drop`` and with some members' content replaced."""
    replace = replace or {}
    out = io.BytesIO()
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            if info.filename != drop:
                dst.writestr(info.filename, replace.get(info.filename, src.read(info)))
    return out.getvalue()


def keypoint_member(archive: Path, index: int = 0) -> str:
    names = sorted(n for n in zipfile.ZipFile(archive).namelist() if n.startswith("keypoints/"))
    return names[index]


# ---------------------------------------------------------------------------- happy path
def test_health_and_docs(stack):
    health = httpx.get(f"{stack.url}/healthz").json()
    assert health == {"status": "ok", "api": "ok", "redis": "ok", "workers": 1,
                      "queued": health["queued"]}
    spec = httpx.get(f"{stack.url}/openapi.json").json()
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/results",
            "/v1/jobs/{job_id}/frames/{frame}/mesh", "/v1/jobs/{job_id}/frames/{frame}/params",
            "/healthz"} <= set(spec["paths"])
    docs = httpx.get(f"{stack.url}/docs")
    assert docs.status_code == 200
    assets = re.findall(r'(?:src|href)="([^"]+)"', docs.text)
    assert len(assets) == 3 and not re.search(r"https?://", docs.text)  # no CDN
    for asset in assets:
        assert httpx.get(f"{stack.url}{asset}").status_code == 200, asset


def test_health_does_not_disclose_where_redis_is(unused_port):
    """With Redis unreachable /healthz says so (503) without its host or port."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    settings = Settings(redis_url=f"redis://127.0.0.1:{unused_port}/0", tokens={"t": "a"})
    with TestClient(create_app(settings)) as app:
        response = app.get("/healthz")
    assert response.status_code == 503 and response.json()["redis"] == "unreachable"
    assert str(unused_port) not in response.text and "127.0.0.1" not in response.text


def test_report_key_of_an_owner_without_a_token():
    """An owner whose token the operator removed has no report key (was a 500: min() of
    nothing); the owner with a token gets a stable one."""
    from service.deps import report_key
    from service.settings import Settings

    settings = Settings(tokens={"alice-token": "alice"})
    assert report_key(settings, "carol", "job1") is None
    assert report_key(settings, "alice", "job1") == report_key(settings, "alice", "job1")
    assert report_key(settings, "alice", "job1") != report_key(settings, "alice", "job2")


def test_full_job_upload_to_download(stack, dataset_zip, body, tmp_path):
    http = client(stack)
    answer = submit(http, dataset_zip, config="rgb", frames="1")
    assert answer.status_code == 202, answer.text
    job = answer.json()
    assert job["status"] == "queued" and job["recordings"] == {REC: 1}
    assert answer.headers["location"] == job["links"]["self"]
    seen = set()
    job = wait(http, job["id"], lambda j: seen.add(j["progress"]["stage"]) or ended(j))
    assert job["status"] == "finished", job
    assert seen - {None} <= {"preparing", "scene", "initialise", "global", "body", "detail",
                             "final", "report", "publishing"} and len(seen - {None}) >= 2
    assert job["progress"]["frames_done"] == job["progress"]["frames_total"] == 1
    assert job["progress"]["fraction"] == 1.0 and job["error"] is None
    timings = job["timings"]
    assert timings["queued_seconds"] >= 0 and timings["run_seconds"] > 0
    assert 0 < timings["seconds_per_frame"] < timings["run_seconds"]
    assert list(timings["steps"]) == ["preparing", "fitting", "report", "publishing"]
    assert timings["seconds_per_frame"] < timings["steps"]["fitting"]
    steps = sum(timings["steps"].values())  # end to end, each rounded to 1 ms
    assert 0.9 * timings["run_seconds"] < steps <= timings["run_seconds"] + 0.004

    results = http.get(job["links"]["results"])
    assert results.status_code == 200
    assert results.headers["content-type"] == "application/zip"
    names = zipfile.ZipFile(io.BytesIO(results.content)).namelist()
    frame = next(n.split("/")[2] for n in names if n.startswith(f"{REC}/results/"))
    assert {f"{REC}/summary.json", f"{REC}/results/{frame}/000.json",
            f"{REC}/meshes/{frame}/000.ply"} <= set(names)

    mesh = http.get(f"/v1/jobs/{job['id']}/frames/{frame}/mesh")
    assert mesh.status_code == 200
    (tmp_path / "m.ply").write_bytes(mesh.content)
    ply = trimesh.load(tmp_path / "m.ply", process=False)
    assert len(ply.vertices) == body.faces.max() + 1 and len(ply.faces) == len(body.faces)
    params = http.get(f"/v1/jobs/{job['id']}/frames/{frame}/params").json()
    assert params["frame"] == frame and params["config"] == "rgb"
    assert http.get(f"/v1/jobs/{job['id']}/frames/nope/params").status_code == 404
    for odd in ("o\u0336" * 200, "a%00b"):  # a name too long for any file system; a NUL
        assert http.get(f"/v1/jobs/{job['id']}/frames/{odd}/params").status_code == 404
        assert http.get(f"/v1/jobs/{job['id']}/report/{odd}").status_code == 404
    assert http.get(f"/v1/jobs/{job['id']}/frames/{frame}/mesh",
                    params={"recording": "Other_1"}).status_code == 404

    assert {"index.html", f"{REC}/report/index.html",
            f"{REC}/report/images/{frame}_camera.jpg"} <= set(names)
    check_report_access(stack, job, frame)

    listed = http.get("/v1/jobs").json()
    assert listed["jobs"][0]["id"] == job["id"]

    assert http.delete(f"/v1/jobs/{job['id']}").status_code == 204
    assert http.get(f"/v1/jobs/{job['id']}").status_code == 404
    assert not (stack.storage_dir / "jobs" / job["id"]).exists()


def check_report_access(stack: LocalStack, job: dict, frame: str) -> None:
    """links.report opens in a cookie-keeping client without a token; others see nothing."""
    browser = httpx.Client(timeout=60)
    index = browser.get(job["links"]["report"])
    assert index.status_code == 200 and index.headers["content-type"].startswith("text/html")
    assert f"{REC}/report/index.html" in index.text
    base = f"{stack.url}/v1/jobs/{job['id']}/report"
    page = browser.get(f"{base}/{REC}/report/index.html")  # the cookie, no key
    assert page.status_code == 200 and "Per frame" in page.text
    image = browser.get(f"{base}/{REC}/report/images/{frame}_camera.jpg")
    assert image.status_code == 200 and image.headers["content-type"] == "image/jpeg"
    assert image.content[:2] == b"\xff\xd8"
    assert httpx.get(f"{base}/{REC}/report/index.html").status_code == 401
    # A wrong key (ASCII or not, query or cookie) reads as an unknown job: same 404 body.
    unknown = f"{stack.url}/v1/jobs/{'0' * 32}/report/"
    for attempt in ({"params": {"key": "0" * 32}}, {"params": {"key": "é"}},
                    {"headers": {"cookie": "prox_report=é".encode()}}):
        known = httpx.get(f"{base}/", **attempt)
        other = httpx.get(unknown, **attempt)
        assert known.status_code == other.status_code == 404, (attempt, known.text)
        assert known.json() == {"detail": f"no job {job['id']}"}
        assert other.json() == {"detail": f"no job {'0' * 32}"}
    bob = client(stack, "bob").get(f"{base}/{REC}/report/index.html")
    assert bob.status_code == 404
    assert client(stack).get(f"{base}/{REC}/report/index.html").status_code == 200
    assert browser.get(f"{base}/{REC}/report/../../../upload.zip").status_code == 404


def test_a_baseline_is_fitted_and_compared_in_the_report(stack, dataset_zip):
    http = client(stack)
    assert submit(http, dataset_zip, config="rgb", baseline="rgb").status_code == 422
    assert submit(http, dataset_zip, baseline="nope").json()["detail"].startswith(
        "unknown baseline 'nope'")
    assert submit(http, dataset_zip, baseline="rgb", report="false").status_code == 422
    assert submit(http, dataset_zip, sequence="true", batch="2").status_code == 422
    answer = submit(http, dataset_zip, config="rgb+penetration", baseline="rgb", frames="1",
                    batch="2")
    assert answer.status_code == 202, answer.text
    stages = set()
    job = wait(http, answer.json()["id"],
               lambda j: stages.add(j["progress"]["stage"]) or ended(j))
    assert job["status"] == "finished" and job["baseline"] == "rgb" and job["batch"] == 2, job
    assert job["progress"]["frames_done"] == 1
    names = zipfile.ZipFile(io.BytesIO(http.get(job["links"]["results"]).content)).namelist()
    assert {f"{REC}/baseline/summary.json", f"{REC}/report/compare.html"} <= set(names)
    browser = httpx.Client(follow_redirects=True)
    assert browser.get(job["links"]["report"]).status_code == 200  # sets the report cookie
    base = f"{stack.url}/v1/jobs/{job['id']}/report/{REC}/report"
    compare = browser.get(f"{base}/compare.html")
    assert compare.status_code == 200 and "rgb+penetration against rgb" in compare.text
    assert 'href="compare.html"' in browser.get(f"{base}/index.html").text
    summary = json.loads(browser.get(f"{stack.url}/v1/jobs/{job['id']}/report/{REC}/"
                                     "baseline/summary.json").text)
    assert summary["config"] == "rgb" and summary["frames_fitted"] == 1


def test_an_smplx_job_uses_the_operators_model_files(stack, dataset_zip):
    http = client(stack)
    answer = submit(http, dataset_zip, config="rgb", frames="1", model="smplx",
                    genders=json.dumps({REC: "neutral"}), report="false")
    assert answer.status_code == 202, answer.text
    job = wait(http, answer.json()["id"], ended)
    assert job["status"] == "finished" and job["model"] == "smplx", job
    names = zipfile.ZipFile(io.BytesIO(http.get(job["links"]["results"]).content)).namelist()
    assert any(n.endswith("/000.pkl") for n in names)
    assert not any("/report/" in n for n in names) and "report" not in job["links"]


def test_list_is_newest_first_and_paginated(stack, dataset_zip):
    http = client(stack)
    ids = [submit(http, dataset_zip, config="rgb", frames="1").json()["id"] for _ in range(2)]
    for job_id in ids:
        http.delete(f"/v1/jobs/{job_id}")  # cancel: keep the worker free
    first = http.get("/v1/jobs", params={"limit": 1}).json()
    assert first["jobs"][0]["id"] == ids[1] and first["total"] >= 2
    assert first["next"] is not None
    second = httpx.get(first["next"], headers=http.headers).json()
    assert second["jobs"][0]["id"] == ids[0]
    assert http.get("/v1/jobs", params={"limit": 1000}).status_code == 422


# ---------------------------------------------------------------------------- cancel, fail
def test_cancel_a_running_and_a_queued_job(stack, dataset_zip):
    http = client(stack)
    first = submit(http, dataset_zip, config="prox").json()
    second = submit(http, dataset_zip, config="rgb", frames="1").json()
    wait(http, first["id"], running)
    answer = http.delete(f"/v1/jobs/{second['id']}")  # still queued behind the first
    assert answer.status_code == 202 and answer.json()["status"] == "cancelled"
    answer = http.delete(f"/v1/jobs/{first['id']}")
    assert answer.status_code == 202 and answer.json()["status"] == "cancelled"
    time.sleep(8)  # the worker stops at its next stage and must not resurrect either job
    for job_id in (first["id"], second["id"]):
        job = http.get(f"/v1/jobs/{job_id}").json()
        assert job["status"] == "cancelled"
        assert http.get(f"/v1/jobs/{job_id}/results").status_code == 409
    assert http.get(f"/v1/jobs/{second['id']}").json()["timings"]["started_at"] is None
    assert httpx.get(f"{stack.url}/healthz").json()["workers"] == 1


def test_a_job_where_every_frame_failed_is_failed_and_the_worker_survives(stack, dataset_zip):
    """Nobody detected in the only frame fitted: the job is failed (it was 'finished' with
    nothing in it), says why, and the worker goes on."""
    http = client(stack)
    empty = keypoint_member(dataset_zip, 0)
    answer = submit(http, edited_zip(dataset_zip, replace={empty: b'{"people": []}'}),
                    config="rgb", frames="1")
    assert answer.status_code == 202, answer.text
    job = wait(http, answer.json()["id"], ended, timeout=120)
    assert job["status"] == "failed", job
    assert job["error"] == (f"no frame could be fitted: {empty}: 'people' is empty: nobody "
                            "detected in this frame"), job["error"]
    assert job["progress"]["frames_failed"] == 1
    assert http.get(f"/v1/jobs/{job['id']}/results").status_code == 409
    assert httpx.get(f"{stack.url}/healthz").json()["workers"] == 1


def test_a_frame_without_people_is_skipped_and_reported(stack, dataset_zip):
    http = client(stack)
    empty = keypoint_member(dataset_zip, 1)
    answer = submit(http, edited_zip(dataset_zip, replace={empty: b'{"people": []}'}),
                    config="rgb")
    assert answer.status_code == 202, answer.text
    job = wait(http, answer.json()["id"], ended)
    assert job["status"] == "finished", job
    assert job["progress"]["frames_done"] == 2 and job["progress"]["frames_failed"] == 1
    [skipped] = job["errors"]
    assert skipped["recording"] == REC
    assert skipped["error"] == f"{empty}: 'people' is empty: nobody detected in this frame"


def test_a_worker_loads_the_report_stack_and_freezes_it_before_forking():
    """What a worker's horses inherit: the fit's and the report's modules imported, every
    report template compiled, L-BFGS's compiled directions loaded, and all of it frozen
    out of the garbage collector's walks (a subprocess, as a worker is: freezing the test
    process would keep its garbage)."""
    probe = ("import gc, sys; from worker.tasks import preload; preload(); "
             "from prox_engine.report import _templates, template_dir; "
             "from prox_engine.lbfgs import _two_loop; "
             "print(gc.get_freeze_count(), len(_templates().cache), "
             "len(list(template_dir().glob('*.html'))), "
             "all(m in sys.modules for m in ('prox_engine.render', 'prox_engine.pipeline')), "
             "len(_two_loop.signatures))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=300, cwd=Path(__file__).parents[1])
    frozen, compiled, templates, imported, directions = done.stdout.split()[-5:]
    assert int(frozen) > 100_000  # the body model's, torch's and pyrender's objects
    assert int(compiled) == int(templates) > 0 and imported == "True"
    assert int(directions) == 1  # no horse loads them (0.3 s a job)


def test_scratch_of_killed_horses_is_cleaned_and_a_job_deleted_as_it_starts(stack, tmp_path):
    """A worker removes the scratch folders dead work-horses left (not those of jobs
    running on this host), and a job deleted before its horse reads it aborts cleanly (it
    was a TypeError on None)."""
    import socket
    import tempfile

    from service.jobs import JobOptions, JobStore
    from service.settings import Settings
    from service.storage import LocalStorage
    from worker.tasks import JobAborted, _Heartbeat, _run, clean_scratch

    settings = Settings(redis_url=stack.redis_url, queue="nobody-listens",
                        storage_dir=tmp_path / "storage")
    store = JobStore(settings)
    running_id, gone_id = store.new_id(), store.new_id()
    owner = "nobody-with-a-token"  # these records stay out of the API users' listings
    store.create(running_id, owner, JobOptions(config="rgb"), {REC: ["f"]}, 1)
    store.start(running_id, 1, f"{socket.gethostname()}:{os.getpid()}")
    live = Path(tempfile.mkdtemp(prefix=f"prox-job-{running_id}-"))
    stale = Path(tempfile.mkdtemp(prefix=f"prox-job-{gone_id}-"))
    assert stale in clean_scratch(store)
    assert live.is_dir() and not stale.exists()
    assert clean_scratch(store, running_id) == [live] and not live.exists()
    assert store.fail(running_id, 1, "test over") and store.delete(running_id)

    store.create(gone_id, owner, JobOptions(config="rgb"), {REC: ["f"]}, 1)
    assert store.cancel(gone_id) and store.delete(gone_id)
    with pytest.raises(JobAborted):
        _run(store, LocalStorage(settings.storage_dir), settings, gone_id, 1, tmp_path,
             _Heartbeat(store, gone_id, 1))


def test_schemathesis_finds_no_server_error_and_no_undocumented_status(stack):
    """Schemathesis generates requests for every operation of /openapi.json (its coverage
    and fuzzing phases, bounded) against the live app and its real Redis."""
    run = subprocess.run(
        [str(Path(sys.executable).parent / "schemathesis"), "run", f"{stack.url}/openapi.json",
         "--checks", "not_a_server_error,status_code_conformance", "--max-examples", "30",
         "--phases", "coverage,fuzzing", "--continue-on-failure", "--request-timeout", "60",
         "-H", f"Authorization: Bearer {TOKENS['alice']}"],
        capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
    assert re.search(r"\d+ generated, \d+ passed", run.stdout), run.stdout[-2000:]


def test_an_api_start_sweeps_job_files_without_a_record(stack):
    """Files of a submission cut off before its job was recorded are removed when an API
    process starts, once old enough not to be a submission in flight; jobs' files stay."""
    from fastapi.testclient import TestClient

    from service.app import ORPHAN_AGE_S, create_app
    from service.settings import Settings

    jobs = stack.storage_dir / "jobs"
    kept = set(os.listdir(jobs))
    old, young = jobs / ("0" * 31 + "1"), jobs / ("0" * 31 + "2")
    for folder in (old, young):
        folder.mkdir()
        (folder / "upload.zip").write_bytes(b"PK")
    stale = time.time() - ORPHAN_AGE_S - 60
    os.utime(old, (stale, stale))
    settings = Settings(redis_url=stack.redis_url, storage_dir=stack.storage_dir,
                        tokens={"t": "someone"})
    with TestClient(create_app(settings)):
        pass
    assert set(os.listdir(jobs)) == kept | {young.name}
    shutil.rmtree(young)


# ---------------------------------------------------------------------------- auth
def test_tokens_see_only_their_own_jobs(stack, dataset_zip):
    alice, bob = client(stack, "alice"), client(stack, "bob")
    anonymous = client(stack, None)
    answer = anonymous.get("/v1/jobs")
    assert answer.status_code == 401 and "bearer" in answer.json()["detail"]
    assert answer.headers["www-authenticate"] == "Bearer"
    wrong = anonymous.get("/v1/jobs", headers={"Authorization": "Bearer not-a-token"})
    assert wrong.status_code == 401 and wrong.json()["detail"] == "invalid API token"
    assert submit(anonymous, dataset_zip).status_code == 401

    job = submit(alice, dataset_zip, config="rgb", frames="1").json()
    for path in ("", "/results", "/frames/x/mesh", "/frames/x/params"):
        assert bob.get(f"/v1/jobs/{job['id']}{path}").status_code == 404
    assert bob.delete(f"/v1/jobs/{job['id']}").status_code == 404
    assert job["id"] not in [j["id"] for j in bob.get("/v1/jobs").json()["jobs"]]
    assert alice.get(f"/v1/jobs/{job['id']}").json()["status"] in ("queued", "running")
    alice.delete(f"/v1/jobs/{job['id']}")


# ---------------------------------------------------------------------------- bad uploads
def _member(name: str, mode: int | None = None) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    if mode is not None:
        info.external_attr = mode << 16
    return info


def _with_extra(source: Path, info: zipfile.ZipInfo, data: bytes) -> bytes:
    out = io.BytesIO(edited_zip(source))
    with zipfile.ZipFile(out, "a") as zf:
        zf.writestr(info, data)
    return out.getvalue()


def _with_copies(source: Path, count: int, recordings: bool = False) -> bytes:
    """Extra frames (or recordings of the same scene) copied from the first frame."""
    out = io.BytesIO(edited_zip(source))
    member = keypoint_member(source)
    with zipfile.ZipFile(source) as src:
        data = src.read(member)
    with zipfile.ZipFile(out, "a") as zf:
        for i in range(count):
            name = (f"keypoints/{REC}{i}/f_keypoints.json" if recordings
                    else member.replace("_keypoints.json", f"{i}_keypoints.json"))
            zf.writestr(name, data)
    return out.getvalue()


def _bomb() -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("keypoints/A_1/f_keypoints.json", b"\0" * (48 << 20))
    return out.getvalue()


BAD_UPLOADS = {
    "not a zip": (lambda z: b"this is not a zip file", {}, 400, None),
    "path traversal": (lambda z: _with_extra(z, _member("../evil.txt"), b"x"), {}, 400,
                       "../evil.txt"),
    "absolute path": (lambda z: _with_extra(z, _member("/etc/evil"), b"x"), {}, 400,
                      "/etc/evil"),
    "symlink": (lambda z: _with_extra(z, _member("link", mode=stat.S_IFLNK | 0o777),
                                      b"/etc/passwd"), {}, 400, "link"),
    "zip bomb": (lambda z: _bomb(), {}, 413, None),
    "unreadable scene mesh": (lambda z: edited_zip(z, replace={
        "scenes/Synthetic.ply": b"ply\nnonsense\n"}), {}, 422, "scenes/Synthetic.ply"),
    "missing cam2world": (lambda z: edited_zip(z, drop="cam2world/Synthetic.json"), {}, 422,
                          "cam2world/Synthetic.json"),
    "bad keypoints": (lambda z: edited_zip(z, replace={keypoint_member(z): b"{not json"}),
                      {}, 422, "keypoints/"),
    "too many frames": (lambda z: _with_copies(z, 4), {}, 422, None),
    "too many recordings": (lambda z: _with_copies(z, 2, recordings=True), {}, 422,
                            "keypoints/"),
    "too large": (lambda z: os.urandom(9 << 20), {}, 413, None),
    "unknown config": (lambda z: z.read_bytes(), {"config": "../../etc/passwd"}, 422, None),
    "frames not positive": (lambda z: z.read_bytes(), {"frames": "0"}, 422, None),
    "unknown model": (lambda z: z.read_bytes(), {"model": "smpl"}, 422, None),
    "no such SMPL-X gender": (lambda z: z.read_bytes(), {"model": "smplx", "gender": "male"},
                              422, None),
    "genders for other recordings": (lambda z: z.read_bytes(),
                                     {"model": "smplx", "genders": '{"Other_1": "neutral"}'},
                                     422, None),
    "genders a list": (lambda z: z.read_bytes(), {"genders": '["female"]'}, 422, None),
    "genders a number": (lambda z: z.read_bytes(), {"genders": "5"}, 422, None),
    "a gender that is an object": (lambda z: z.read_bytes(),
                                   {"genders": json.dumps({REC: {"a": ["female"]}})}, 422, None),
    "genders nested deeply": (lambda z: z.read_bytes(),
                              {"genders": "[" * 100_000 + "]" * 100_000}, 422, None),
}


def test_listing_offsets_past_any_integer_are_a_json_422(stack):
    answer = client(stack).get("/v1/jobs", params={"offset": "75794324159085474796797952"})
    assert answer.status_code == 422 and answer.json()["detail"]


@pytest.mark.parametrize("case", list(BAD_UPLOADS))
def test_bad_uploads_are_rejected_before_queueing(stack, dataset_zip, case):
    http = client(stack)
    make, form, status, file = BAD_UPLOADS[case]
    before = http.get("/v1/jobs").json()["total"]
    answer = submit(http, make(dataset_zip), **form)
    assert answer.status_code == status, answer.text
    body = answer.json()
    assert body["detail"]
    if file is not None:
        assert body["file"].startswith(file), body
    assert http.get("/v1/jobs").json()["total"] == before
    stored = stack.storage_dir / "jobs"
    assert sorted(os.listdir(stored) if stored.exists() else []) == sorted(
        j["id"] for j in http.get("/v1/jobs", params={"limit": 100}).json()["jobs"])


def test_a_streamed_upload_is_cut_off_at_the_limit(stack):
    """No Content-Length (chunked): the limit applies while the body streams in."""
    def body():
        yield (b'--b\r\nContent-Disposition: form-data; name="file"; filename="x.zip"\r\n'
               b"Content-Type: application/zip\r\n\r\n")
        for _ in range(12):
            yield os.urandom(1 << 20)
        yield b"\r\n--b--\r\n"

    answer = client(stack).post("/v1/jobs", content=body(),
                                headers={"Content-Type": "multipart/form-data; boundary=b"})
    assert answer.status_code == 413
    assert answer.json()["detail"] == "upload larger than the limit of 8 MB"


# ---------------------------------------------------------------------------- dying workers
def _pid(job: dict) -> int:
    return int(job["worker"].rsplit(":", 1)[1])


def test_a_killed_work_horse_is_retried_once_then_failed(stack, dataset_zip):
    http = client(stack)
    job = submit(http, dataset_zip, config="prox").json()
    job = wait(http, job["id"], running)
    os.kill(_pid(job), signal.SIGKILL)
    job = wait(http, job["id"], lambda j: j["attempt"] == 2 and running(j), timeout=120)
    assert job["error"].startswith("attempt 1 failed: its worker process died (signal 9)")
    os.kill(_pid(job), signal.SIGKILL)
    job = wait(http, job["id"], ended, timeout=60)
    assert job["status"] == "failed" and job["attempt"] == 2
    assert "its worker process died (signal 9)" in job["error"]
    assert "attempt 2 of 2" in job["error"]
    assert httpx.get(f"{stack.url}/healthz").json()["workers"] == 1


def test_a_job_whose_worker_vanished_is_reaped_and_retried(stack, dataset_zip):
    http = client(stack)
    job = submit(http, dataset_zip, config="rgb", frames="1").json()
    job = wait(http, job["id"], running)
    horse = _pid(job)
    stack.workers[0].kill()  # the whole worker: nobody is left to report the loss
    os.kill(horse, signal.SIGKILL)
    stack.workers[0].wait()
    job = wait(http, job["id"], lambda j: j["attempt"] == 2, timeout=60)
    assert job["status"] == "queued" and "without a heartbeat" in job["error"]
    # As prox serve does: the dead worker is replaced at once, under a fresh name (its
    # old one is still registered in Redis, and RQ refuses a live-looking name).
    assert stack.supervise() == ["worker-0"]
    job = wait(http, job["id"], ended, timeout=300)
    assert job["status"] == "finished" and job["attempt"] == 2 and job["error"] is None


def test_a_job_a_worker_took_but_never_started_is_retried(stack):
    """A worker takes an attempt off the queue (RQ moves it to its intermediate list) and
    dies, or Redis is killed, before the attempt starts: the record stays queued and no
    worker would ever run it. The reaper retries it once it has waited ``stale_after_s``.
    A queue of its own keeps the stack's worker away from it."""
    from rq import Queue

    from service.jobs import JobOptions, JobStore
    from service.settings import Settings

    store = JobStore(Settings(redis_url=stack.redis_url, queue="taken-test", stale_after_s=1))
    job_id = store.new_id()
    store.create(job_id, "alice", JobOptions(config="rgb"), {REC: ["f1"]}, 1)
    assert store.reap() == []  # still waiting in the queue: nothing to do
    assert Queue.lmove(store.queue.connection, store.queue.key, timeout=None)  # taken
    assert store.reap() == []  # marked, not yet retried
    assert store.get(job_id)["attempt"] == 1
    time.sleep(1.2)
    assert store.reap() == [job_id]
    record = store.get(job_id)
    assert record["status"] == "queued" and record["attempt"] == 2
    assert "never started it" in record["error"]
    assert store.queue.get_job_ids() == [f"{job_id}-2"]
    assert store.reap() == []  # the new attempt waits in the queue


def test_a_redis_restart_loses_no_job_and_the_api_says_503_meanwhile(stack, dataset_zip):
    """Redis killed mid-job: every /v1 route is a JSON 503 with Retry-After while it is
    down; restarted from its append-only file, it still has both jobs, the busy worker
    rides out the outage, and each job ends finished exactly once."""
    http = client(stack)
    running_job = submit(http, dataset_zip, config="rgb", frames="2").json()
    queued_job = submit(http, dataset_zip, config="rgb", frames="1").json()
    wait(http, running_job["id"], running)
    time.sleep(1.5)  # append-only file synced every second
    alive = [w for w in stack.workers if w.poll() is None]
    stack.redis.kill()
    stack.redis.wait()
    for path in ("/v1/jobs", f"/v1/jobs/{running_job['id']}"):
        down = http.get(path)
        assert down.status_code == 503, down.text
        assert down.headers["retry-after"] == "5" and "unreachable" in down.json()["detail"]
    stored = set(os.listdir(stack.storage_dir / "jobs"))
    refused = submit(http, dataset_zip, config="rgb", frames="1")
    assert refused.status_code == 503, refused.text
    assert set(os.listdir(stack.storage_dir / "jobs")) == stored  # its upload was removed
    time.sleep(3)
    stack.restart_redis()
    for job in (running_job, queued_job):
        final = wait(http, job["id"], ended, timeout=300)
        assert final["status"] == "finished", final
        assert final["progress"]["frames_done"] == final["progress"]["frames_total"]
    assert alive and all(w.poll() is None for w in alive)  # the workers rode it out
    deadline = time.monotonic() + 60
    while httpx.get(f"{stack.url}/healthz").json()["workers"] < 1:
        assert time.monotonic() < deadline, "no worker came back"
        time.sleep(1)
