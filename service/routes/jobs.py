"""``/v1/jobs``: submit a sequence, follow it, download its results, cancel or delete it."""
from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, File, Form, Query, Request, Response, UploadFile
from fastapi.responses import StreamingResponse

from prox_engine.config import BODY_MODELS, CONFIG_DIR, GENDERS, load_config

from ..deps import OwnerDep, SettingsDep, StorageDep, StoreDep, report_key
from ..errors import ApiError, documented
from ..jobs import TERMINAL, JobOptions
from ..schemas import JobPage, JobView, job_view
from ..settings import Settings
from ..storage import Storage
from ..upload import UploadError, validate_upload

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses=documented(401, 422, 503))
CONFIGS = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
_CHUNK = 1 << 20
MAX_OFFSET = 10 ** 9  # far past any listing, well inside Redis's integer range


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _view(record: dict, request: Request, settings: Settings) -> JobView:
    return job_view(record, _base(request),
                    report_key(settings, record["owner"], record["id"]))


def _own_job(store, job_id: str, owner: str) -> dict:
    """The job if it exists and belongs to the caller (else 404: others' jobs are unseen)."""
    record = store.get(job_id)
    if record is None or record["owner"] != owner:
        raise ApiError(404, f"no job {job_id}")
    return record


@router.post("", status_code=202, response_model=JobView, responses=documented(400, 413),
             summary="Submit a sequence (a zip in the PROX layout) for fitting")
def submit(request: Request, response: Response, owner: OwnerDep, settings: SettingsDep,
           store: StoreDep, storage: StorageDep,
           file: Annotated[UploadFile, File(description="zip of a PROX-layout directory")],
           config: Annotated[str, Form(description=f"one of {', '.join(CONFIGS)}")] = "prox",
           frames: Annotated[int | None, Form(ge=1, description="fit only the first N "
                                                                "frames of each recording")] = None,
           sequence: Annotated[bool, Form(description="warm-start each frame from the "
                                                      "previous one (prox also fits it from "
                                                      "scratch and keeps the fit on the "
                                                      "path of least motion)")] = False,
           report: Annotated[bool, Form(description="HTML reports with renders")] = True,
           render_every: Annotated[int, Form(ge=1, description="render every k-th frame in "
                                                               "the reports")] = 1,
           model: Annotated[str, Form(description="anny (free, default) or smplx (the "
                                                  "operator's licensed files)")] = "anny",
           gender: Annotated[str, Form(description="neutral, male or female")] = "neutral",
           genders: Annotated[str | None, Form(description='per recording, JSON: '
                                                           '{"<recording>": "female"}')] = None,
           hand_pca: Annotated[int, Form(ge=0, le=45, description="SMPL-X hand PCA "
                                                                  "components; 0: every "
                                                                  "finger joint")] = 12,
           baseline: Annotated[str | None, Form(description="also fit this configuration "
                                                            "(e.g. rgb) and add its "
                                                            "comparison, compare.html, to "
                                                            "each report")] = None,
           batch: Annotated[int, Form(ge=1, le=64, description="frames of a recording "
                                                             "fitted together (not with "
                                                             "sequence)")] = 1
           ) -> JobView:
    for option, name in (("config", config), ("baseline", baseline)):
        if name is not None and name not in CONFIGS:
            raise ApiError(422, f"unknown {option} '{name}' (choose one of "
                                f"{', '.join(CONFIGS)})")
    if sequence and batch > 1:
        raise ApiError(422, "sequence mode fits one frame after another: batch must be 1")
    if baseline == config:
        raise ApiError(422, f"baseline '{baseline}' is the job's own configuration")
    if baseline is not None and not report:
        raise ApiError(422, "a baseline is fitted for the reports' comparison: it needs "
                            "report=true")
    job_id = store.new_id()
    with tempfile.NamedTemporaryFile(suffix=".zip") as upload:
        shutil.copyfileobj(file.file, upload, _CHUNK)
        upload.flush()
        try:
            summary = validate_upload(Path(upload.name), settings.upload_limits(), frames,
                                      needs_depth=any(load_config(c).uses("depth")
                                                      for c in (config, baseline) if c))
        except UploadError as exc:
            raise ApiError(exc.status, str(exc), file=exc.file) from exc
        per_recording = _check_body(settings, model, gender, genders, summary.recordings)
        storage.put_file(f"jobs/{job_id}/upload.zip", Path(upload.name))
        size = Path(upload.name).stat().st_size
    options = JobOptions(config, frames, sequence, report, render_every, model, gender,
                         per_recording, hand_pca, baseline, batch)
    try:
        record = store.create(job_id, owner, options, summary.recordings, size)
    except BaseException:  # e.g. Redis down (a 503): no job, so no stored upload either
        storage.delete_prefix(f"jobs/{job_id}")
        raise
    view = _view(record, request, settings)
    response.headers["Location"] = view.links["self"]
    return view


def _check_body(settings: Settings, model: str, gender: str, genders: str | None,
                recordings: dict[str, list[str]]) -> dict[str, str] | None:
    """422 unless the body model and genders can be served; the per-recording genders."""
    if model not in BODY_MODELS:
        raise ApiError(422, f"unknown model '{model}' (choose {' or '.join(BODY_MODELS)})")
    per_recording = None
    if genders:
        try:
            per_recording = json.loads(genders)
        except RecursionError as exc:
            raise ApiError(422, "'genders' is nested too deeply") from exc
        except ValueError as exc:
            raise ApiError(422, f"'genders' is not JSON ({exc})") from exc
        if (not isinstance(per_recording, dict) or not set(per_recording) <= set(recordings)
                or not all(isinstance(g, str) for g in per_recording.values())):
            raise ApiError(422, "'genders' must map recordings of the upload to gender names")
    wanted = {gender, *(per_recording or {}).values()}
    if not wanted <= set(GENDERS):
        raise ApiError(422, f"unknown gender in {sorted(wanted)} (choose "
                            f"{', '.join(GENDERS)})")
    if model == "smplx":
        if settings.model_dir is None:
            raise ApiError(422, "this service has no SMPL-X model files (its operator mounts "
                                "them and sets PROX_MODEL_DIR); use model=anny")
        for g in sorted(wanted):
            if not (settings.model_dir / f"SMPLX_{g.upper()}.npz").is_file():
                raise ApiError(422, f"this service has no {g} SMPL-X model")
    return per_recording


@router.get("", response_model=JobPage, summary="The caller's jobs, newest first")
def list_jobs(request: Request, owner: OwnerDep, store: StoreDep, settings: SettingsDep,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
              limit: Annotated[int, Query(ge=1, le=100)] = 20) -> JobPage:
    records, total = store.list(owner, offset, limit)
    base = _base(request)
    following = (f"{base}/v1/jobs?offset={offset + limit}&limit={limit}"
                 if offset + limit < total else None)
    return JobPage(jobs=[_view(r, request, settings) for r in records], total=total,
                   offset=offset,
                   limit=limit, next=following)


@router.get("/{job_id}", response_model=JobView, responses=documented(404),
            summary="Status, progress and timings")
def get_job(job_id: str, request: Request, owner: OwnerDep, store: StoreDep,
            settings: SettingsDep) -> JobView:
    return _view(_own_job(store, job_id, owner), request, settings)


def _finished(store, job_id: str, owner: str) -> dict:
    record = _own_job(store, job_id, owner)
    if record["status"] != "finished":
        raise ApiError(409, f"job {job_id} is {record['status']}: results exist only for "
                            "finished jobs")
    return record


@router.get("/{job_id}/results", summary="A zip of the results directory",
            response_class=StreamingResponse,
            responses={200: {"content": {"application/zip": {}}},
                       **documented(404, 409, 410)})
def results(job_id: str, owner: OwnerDep, store: StoreDep,
            storage: StorageDep) -> StreamingResponse:
    _finished(store, job_id, owner)
    key = f"jobs/{job_id}/results.zip"
    size = storage.size(key)
    if size is None:
        raise ApiError(410, f"the results of job {job_id} are no longer in storage")
    headers = {"Content-Disposition": f'attachment; filename="prox-{job_id}.zip"',
               "Content-Length": str(size)}
    return StreamingResponse(storage.chunks(key), media_type="application/zip",
                             headers=headers)


def _frame_key(store, storage: Storage, job_id: str, owner: str, frame: str,
               recording: str | None, kind: str) -> str:
    record = _finished(store, job_id, owner)
    folder, name = {"mesh": ("meshes", "000.ply"), "params": ("results", "000.json")}[kind]
    candidates = [recording] if recording else list(record["recordings"])
    if recording and recording not in record["recordings"]:
        raise ApiError(404, f"job {job_id} has no recording {recording}")
    if frame in (".", ".."):
        raise ApiError(404, f"no frame {frame}")
    keys = [f"jobs/{job_id}/results/{rec}/{folder}/{frame}/{name}" for rec in candidates]
    found = [k for k in keys if storage.size(k) is not None]
    if not found:
        raise ApiError(404, f"job {job_id} has no fitted frame {frame}")
    if len(found) > 1:
        raise ApiError(409, f"frame {frame} is in several recordings: add ?recording=NAME")
    return found[0]


RecordingQuery = Annotated[str | None, Query(description="needed when several recordings "
                                                         "have a frame of this name")]


@router.get("/{job_id}/frames/{frame}/mesh", summary="One frame's fitted mesh (PLY, camera "
            "frame)", response_class=StreamingResponse,
            responses={200: {"content": {"application/octet-stream": {}}},
                       **documented(404, 409)})
def frame_mesh(job_id: str, frame: str, owner: OwnerDep, store: StoreDep, storage: StorageDep,
               recording: RecordingQuery = None) -> StreamingResponse:
    key = _frame_key(store, storage, job_id, owner, frame, recording, "mesh")
    return StreamingResponse(storage.chunks(key), media_type="application/octet-stream",
                             headers={"Content-Disposition":
                                      f'attachment; filename="{frame}.ply"'})


@router.get("/{job_id}/frames/{frame}/params", summary="One frame's fitted parameters, "
            "losses and statistics", responses=documented(404, 409))
def frame_params(job_id: str, frame: str, owner: OwnerDep, store: StoreDep,
                 storage: StorageDep, recording: RecordingQuery = None) -> dict:
    key = _frame_key(store, storage, job_id, owner, frame, recording, "params")
    with storage.open(key) as handle:
        return json.load(handle)


@router.delete("/{job_id}", status_code=204,
               responses={202: {"model": JobView}, **documented(404)},
               summary="Cancel a queued or running job; delete a finished one and its files")
def delete_job(job_id: str, request: Request, owner: OwnerDep, store: StoreDep,
               storage: StorageDep, settings: SettingsDep) -> Response:
    record = _own_job(store, job_id, owner)
    if record["status"] not in TERMINAL:
        cancelled = store.cancel(job_id)
        if cancelled is not None:
            view = _view(cancelled, request, settings)
            return Response(view.model_dump_json(), status_code=202,
                            media_type="application/json")
        # It ended meanwhile: delete it like any finished job.
    if store.delete(job_id):
        storage.delete_prefix(f"jobs/{job_id}")
    return Response(status_code=204)
