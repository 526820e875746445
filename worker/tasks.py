"""The work of one job attempt, run by an RQ work-horse: fetch the upload, fit every
recording with the engine, publish the results, and keep the job record current."""
from __future__ import annotations

import contextlib
import gc
import os
import shutil
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

from rq.timeouts import JobTimeoutException

from prox_engine.body.base import BodyModel
from prox_engine.config import FitConfig
from prox_engine.errors import InputError
from service.jobs import JobOptions, JobStore
from service.settings import Settings
from service.storage import LocalStorage, Storage, zip_tree
from service.upload import UploadError, extract_upload

HEARTBEAT_S = 5.0
BASELINE = "baseline"  # results/<rec>/baseline/: the fit with the job's baseline configuration
SCRATCH_PREFIX = "prox-job-"  # a job attempt's scratch folder: prox-job-<id>-<random>


def clean_scratch(store: JobStore, job_id: str | None = None) -> list[Path]:
    """Remove the scratch folders a killed work-horse left behind: those of ``job_id``, or
    (at start-up) every one whose job is not running in a live process on this host."""
    host = socket.gethostname()
    removed = []
    for folder in Path(tempfile.gettempdir()).glob(f"{SCRATCH_PREFIX}{job_id or ''}*"):
        owner = folder.name.removeprefix(SCRATCH_PREFIX).rsplit("-", 1)[0]
        if job_id is None:
            record = store.get(owner)
            where = (record or {}).get("worker") or ""
            name, _, pid = where.rpartition(":")
            if (record is not None and record["status"] == "running" and name == host
                    and pid.isdigit() and Path(f"/proc/{pid}").exists()):
                continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


_BODIES: dict[tuple, BodyModel] = {}  # loaded in this process; forked horses inherit them


def body_for(config: FitConfig, gender: str) -> BodyModel:
    """The body model a job's configuration names, loaded once per process: the worker
    loads the default (anny) before it forks its first horse (:func:`preload`), so that no
    job pays for loading it."""
    from prox_engine.body import load_body

    key = (("anny",) if config.model == "anny" else
           (config.model, gender, config.model_path, config.hand_pca, config.body_segments,
            config.vposer_path))
    if key not in _BODIES:
        _BODIES[key] = load_body(config, gender)
    return _BODIES[key]


def preload() -> float:
    """In the worker before it forks: load the default body model and run it forwards and
    backwards once (which loads its compiled kernels), load L-BFGS's compiled directions
    (0.3 s a job otherwise), import the fit's modules and the report's rendering stack,
    compile the report's templates, and freeze all that out of the garbage collector's
    reach, so that a horse's full collections (pyrender runs one as each report's renderer
    closes: 0.5 s over the loaded model, two fits running beside it) walk only what its
    job made. Returns the seconds it took."""
    import torch

    import prox_engine.pipeline  # noqa: F401  (the fit's modules: OpenCV among them)
    from prox_engine.config import load_config
    from prox_engine.lbfgs import compile_directions
    from prox_engine.report import warm_up

    start = time.perf_counter()
    torch.set_num_threads(int(os.environ.get("PROX_THREADS", "1")))
    body = body_for(load_config("prox"), "neutral")
    params = body.init_params(1)
    params["body_pose"].requires_grad_(True)
    body(params).vertices.sum().backward()
    compile_directions()
    warm_up()
    gc.freeze()
    return time.perf_counter() - start


class JobAborted(Exception):
    """The job was cancelled, or this attempt superseded: stop without publishing."""


class _Heartbeat(threading.Thread):
    """Keeps the record's heartbeat fresh while a long step (an SDF, a stage) runs."""

    def __init__(self, store: JobStore, job_id: str, attempt: int) -> None:
        super().__init__(daemon=True, name=f"heartbeat-{job_id}")
        self.store, self.job_id, self.attempt = store, job_id, attempt
        self.stopped = threading.Event()
        self.current = True

    def run(self) -> None:
        while not self.stopped.wait(HEARTBEAT_S):
            self.current = self.store.progress(self.job_id, self.attempt)


def run_job(job_id: str, attempt: int) -> str:
    """RQ entry point; returns the attempt's outcome (the job record has the details)."""
    settings = Settings.from_env()
    store = JobStore(settings)
    if store.start(job_id, attempt, f"{socket.gethostname()}:{os.getpid()}") is None:
        return "skipped: cancelled or superseded"
    heartbeat = _Heartbeat(store, job_id, attempt)
    heartbeat.start()
    scratch = Path(tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{job_id}-"))
    try:
        return _run(store, LocalStorage(settings.storage_dir), settings, job_id, attempt,
                    scratch, heartbeat)
    except JobAborted:
        return "aborted"
    except (InputError, UploadError) as exc:
        store.fail(job_id, attempt, str(exc))
        return "failed"
    except JobTimeoutException as exc:
        store.fail(job_id, attempt, f"took longer than its time limit ({exc})")
        return "failed"
    except Exception as exc:  # noqa: BLE001 - the record must say why, then RQ keeps the trace
        store.fail(job_id, attempt, f"internal error ({type(exc).__name__}: {exc})")
        raise
    finally:
        heartbeat.stopped.set()
        shutil.rmtree(scratch, ignore_errors=True)


def _reports(out: Path, data: Path, recordings: list[str], options: JobOptions, job_id: str,
             update: Callable[..., None]) -> list[dict]:
    """HTML reports of the fitted recordings and the job's index page; a recording whose
    report fails is noted, not fatal."""
    from prox_engine.report import build_report, write_index

    errors = []
    for name in recordings:
        if not (out / name / "summary.json").exists():
            continue
        update(stage="report", recording=name)
        compare = out / name / BASELINE
        try:
            build_report(out / name, data=data, every=options.render_every,
                         baseline=compare if compare.is_dir() else None)
        except Exception as exc:  # noqa: BLE001 - the fit stands without its report
            errors.append({"recording": name, "error": f"report failed ({exc})"})
    write_index(out, recordings, f"prox job {job_id}")
    return errors


def _run(store: JobStore, storage: Storage, settings: Settings, job_id: str, attempt: int,
         scratch: Path, heartbeat: _Heartbeat) -> str:
    import torch

    from prox_engine.pipeline import fit_recording

    record = store.get(job_id)
    if record is None:  # deleted since it started
        raise JobAborted
    options = JobOptions(**record["options"])
    started = time.perf_counter()
    torch.set_num_threads(int(os.environ.get("PROX_THREADS", "1")))
    torch.manual_seed(0)  # forked work-horses share the parent's random state

    def update(**fields: object) -> None:
        if not heartbeat.current or not store.progress(job_id, attempt, **fields):
            raise JobAborted

    steps: dict[str, float] = {}  # seconds a step of the job took, in order

    def step_ended(name: str, since: float) -> float:
        now = time.perf_counter()
        steps[name] = round(now - since, 3)
        return now

    update(stage="preparing")
    upload = scratch / "upload.zip"
    storage.get_file(f"jobs/{job_id}/upload.zip", upload)
    data = scratch / "data"
    base = extract_upload(upload, data, settings.upload_limits(),
                          options.frames).relative_to(data)
    upload.unlink()
    config = options.fit_config(settings.model_dir)
    baseline = (options.fit_config(settings.model_dir, options.baseline)
                if options.baseline else None)
    out = scratch / "results"
    mark = step_ended("preparing", started)
    done = failed = 0
    errors: list[dict] = []
    seconds: list[float] = []
    for name in record["recordings"]:
        def progress(n: int, total: int, frame: str, rec: str = name, offset: int = done
                     ) -> None:
            update(frames_done=offset + n, recording=rec)

        def on_stage(stage: str, rec: str = name, prefix: str = "") -> None:
            update(stage=prefix + stage, recording=rec)

        gender = options.gender_of(name)
        body = body_for(config, gender)
        try:
            # From inside the unpacked upload, so that every path in an error message or
            # summary reads as it does in the user's zip.
            with contextlib.chdir(data):
                result = fit_recording(base, name, out, config, body,
                                       max_frames=options.frames, sequence=options.sequence,
                                       progress=progress, on_stage=on_stage,
                                       source=f"the upload of job {job_id}")
        except InputError as exc:
            errors.append({"recording": name, "error": str(exc)})
            done += record["recordings"][name]
            continue
        if baseline is not None and result.summary["frames_fitted"]:
            # the same frames with the baseline configuration: results/<rec>/baseline/
            with contextlib.chdir(data):
                fit_recording(base, name, scratch / BASELINE, baseline, body,
                              max_frames=options.frames, sequence=options.sequence,
                              on_stage=lambda stage, rec=name: on_stage(stage, rec,
                                                                        "baseline "),
                              source=f"the upload of job {job_id}")
            (scratch / BASELINE / name).rename(out / name / BASELINE)
        summary = result.summary
        done += summary["frames_fitted"] + summary["frames_failed"]
        failed += summary["frames_failed"]
        errors += [{"recording": name, "frame": f["frame"], "error": f["error"]}
                   for f in summary["failures"]]
        if summary["seconds_per_frame"] is not None:
            seconds.append(summary["seconds_per_frame"])
    if done == failed + sum(record["recordings"][e["recording"]] for e in errors
                            if "frame" not in e):  # nothing fitted: every frame failed
        shown = "; ".join(e["error"] for e in errors[:3])
        more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
        store.fail(job_id, attempt, f"no frame could be fitted: {shown}{more}",
                   frames_done=done, frames_failed=failed, errors=errors)
        return "failed"
    mark = step_ended("fitting", mark)
    if options.report:
        errors += _reports(out, data / base, list(record["recordings"]), options, job_id,
                           update)
        mark = step_ended("report", mark)

    update(stage="publishing", frames_done=done, frames_failed=failed)
    archive = scratch / "results.zip"
    zip_tree(out, archive)
    storage.put_tree(f"jobs/{job_id}/results", out)
    storage.put_file(f"jobs/{job_id}/results.zip", archive)
    step_ended("publishing", mark)
    timings = {"run_seconds": round(time.perf_counter() - started, 3),
               "seconds_per_frame": round(sum(seconds) / len(seconds), 3) if seconds else None,
               "steps": steps}
    if not store.finish(job_id, attempt, frames_done=done, frames_failed=failed,
                        errors=errors, timings=timings):
        if store.get(job_id) is None:  # deleted while publishing: leave nothing behind
            storage.delete_prefix(f"jobs/{job_id}")
        raise JobAborted
    return "finished"

