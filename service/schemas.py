"""The JSON shapes the API answers with (they document themselves at ``/docs``)."""
from __future__ import annotations

from datetime import datetime, timezone

from pydantic import BaseModel


class Progress(BaseModel):
    frames_done: int
    frames_total: int
    frames_failed: int
    fraction: float
    recording: str | None
    stage: str | None


class Timings(BaseModel):
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    queued_seconds: float | None
    run_seconds: float | None
    seconds_per_frame: float | None
    # seconds each step of the run took, in order: preparing (the upload unpacked),
    # fitting (scenes and frames, the baseline's too), report, publishing
    steps: dict[str, float]


class JobView(BaseModel):
    id: str
    status: str  # queued | running | finished | failed | cancelled
    config: str
    frames: int | None
    sequence: bool
    report: bool
    render_every: int
    model: str
    gender: str
    baseline: str | None  # configuration also fitted for the reports' compare.html
    batch: int  # frames of a recording fitted together
    recordings: dict[str, int]  # recording -> frames to fit
    progress: Progress
    timings: Timings
    attempt: int  # 2 after a retry (the first attempt's worker died)
    worker: str | None  # host:pid of the process running the attempt
    error: str | None
    errors: list[dict]  # skipped frames and failed recordings
    links: dict[str, str]


class JobPage(BaseModel):
    jobs: list[JobView]
    total: int
    offset: int
    limit: int
    next: str | None


class Health(BaseModel):
    status: str  # ok | degraded
    api: str
    redis: str
    workers: int
    queued: int | None


def _time(seconds: float | None) -> datetime | None:
    return datetime.fromtimestamp(seconds, timezone.utc) if seconds else None


def job_view(record: dict, base: str, report_key: str | None = None) -> JobView:
    """A job record as the API shows it; ``base`` is the API root URL (no trailing /),
    ``report_key`` opens its report in a browser."""
    options, job_id = record["options"], record["id"]
    started, finished = record["started_at"], record["finished_at"]
    total = record["frames_total"]
    links = {"self": f"{base}/v1/jobs/{job_id}"}
    if record["status"] == "finished":
        links["results"] = f"{base}/v1/jobs/{job_id}/results"
        links["frame_mesh"] = f"{base}/v1/jobs/{job_id}/frames/{{frame}}/mesh"
        links["frame_params"] = f"{base}/v1/jobs/{job_id}/frames/{{frame}}/params"
        if options["report"] and report_key:
            links["report"] = f"{base}/v1/jobs/{job_id}/report/?key={report_key}"
    return JobView(
        id=job_id, status=record["status"], config=options["config"],
        frames=options["frames"], sequence=options["sequence"],
        report=options["report"], render_every=options["render_every"],
        model=options["model"], gender=options["gender"],
        baseline=options.get("baseline"), batch=options.get("batch", 1),
        recordings=record["recordings"],
        progress=Progress(frames_done=record["frames_done"], frames_total=total,
                          frames_failed=record["frames_failed"],
                          fraction=round(record["frames_done"] / total, 4) if total else 0.0,
                          recording=record["recording"], stage=record["stage"]),
        timings=Timings(created_at=_time(record["created_at"]), started_at=_time(started),
                        finished_at=_time(finished),
                        queued_seconds=round(started - record["created_at"], 3)
                        if started else None,
                        run_seconds=record["timings"].get("run_seconds"),
                        seconds_per_frame=record["timings"].get("seconds_per_frame"),
                        steps=record["timings"].get("steps", {})),
        attempt=record["attempt"], worker=record["worker"], error=record["error"],
        errors=record["errors"],
        links=links)
