"""Load check (not a unit test): ``python -m service.loadcheck --jobs 50 --workers 2``.

Starts a local service, submits N one-frame jobs at once, kills Redis when a third have
finished and restarts it from its append-only file, waits for all of them and checks that
every job finished exactly once with its results; then kills a work-horse mid-job and,
separately, a whole worker, and checks that both jobs are retried and finish instead of
hanging. Prints the figures and writes them to ``OUT/loadcheck.json``.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import secrets
import shutil
import signal
import statistics
import sys
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

from .client import ApiClient
from .jobs import JobStore
from .local import LocalStack
from .settings import Settings
from .storage import zip_tree

STALE_S = 30
REDIS_DOWN_S = 5  # how long Redis stays down in the outage mid-run


def _wait_all(client: ApiClient, ids: list[str], timeout: float,
              outage: Callable[[], None] | None = None) -> dict[str, dict]:
    """Poll until every job has ended; ``outage()`` runs once, when a third have finished."""
    deadline = time.monotonic() + timeout
    while True:
        jobs = {i: client.job(i) for i in ids}
        states = [j["status"] for j in jobs.values()]
        finished = sum(s == "finished" for s in states)
        print(f"  {finished} finished, "
              f"{sum(s == 'running' for s in states)} running, "
              f"{sum(s == 'queued' for s in states)} queued", flush=True)
        if all(s in ("finished", "failed", "cancelled") for s in states):
            return jobs
        if outage is not None and finished >= len(ids) / 3:
            outage()
            outage = None
        if time.monotonic() > deadline:
            raise TimeoutError(f"jobs still pending after {timeout} s: {states}")
        time.sleep(5)


def _check_results(client: ApiClient, job_id: str) -> int:
    answer = client.http.get(f"/v1/jobs/{job_id}/results")
    answer.raise_for_status()
    with zipfile.ZipFile(io.BytesIO(answer.content)) as zf:
        summaries = [json.loads(zf.read(n)) for n in zf.namelist()
                     if n.endswith("/summary.json")]
    return sum(s["frames_fitted"] for s in summaries)


def _kill_check(client: ApiClient, stack: LocalStack, archive: Path, whole_worker: bool
                ) -> dict:
    """Kill a job's work-horse (or its whole worker) mid-fit; time until it finishes. The
    kill lands in any stage of the job's work (loading its scene, the start search, the
    configuration's stages): a one-frame job spends a fraction of a second in any one, and
    a poll for one stage alone can miss it."""
    from prox_engine.config import load_config

    at_work = {"scene", "initialise", *(stage.name for stage in load_config("prox").stages)}
    job = client.submit(archive, config="prox")
    while not (job["status"] == "running" and job["progress"]["stage"] in at_work):
        if job["status"] not in ("queued", "running"):
            raise RuntimeError(f"job {job['id']} ended ({job['status']}) before it was seen "
                               "mid-fit")
        time.sleep(0.05)
        job = client.job(job["id"])
    horse = int(job["worker"].rsplit(":", 1)[1])
    killed = time.monotonic()
    if whole_worker:
        worker = next(w for w in stack.workers if w.pid == _parent_pid(horse))
        worker.kill()
        worker.wait()
    os.kill(horse, signal.SIGKILL)
    while (job := client.job(job["id"]))["attempt"] == 1 and job["status"] == "running":
        if time.monotonic() - killed > STALE_S * 4:
            raise TimeoutError(f"job {job['id']} still on attempt 1 after the kill")
        time.sleep(0.5)
    retried = time.monotonic() - killed
    if whole_worker:
        stack.add_worker()
    final = client.wait(job["id"], timeout=600, poll=1)
    return {"killed": "whole worker" if whole_worker else "work-horse",
            "status": final["status"], "attempt": final["attempt"],
            "seconds_to_retry": round(retried, 1),
            "seconds_to_finish": round(time.monotonic() - killed, 1),
            "error_after_retry": job["error"]}


def _parent_pid(pid: int) -> int:
    """A work-horse's parent: its RQ worker."""
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.loadcheck", description=__doc__)
    parser.add_argument("--jobs", type=int, default=50)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("loadcheck_output"))
    args = parser.parse_args(argv)

    from prox_engine.config import load_config
    from prox_engine.dataset import Recording
    from prox_engine.pipeline import load_scene
    from prox_engine.synthetic import make_sitting_dataset

    # A fresh service each run: a previous run's Redis file would list its jobs too.
    shutil.rmtree(args.out / "service", ignore_errors=True)
    data = make_sitting_dataset(args.out / "data", frames=2, face_size=0.12)
    # The scene's SDF goes to the workers' cache before the clock starts, as it is for
    # every job after a scene's first: what is measured is the per-job cost.
    load_scene(Recording(data, "Synthetic_00000_01"), load_config("rgb").sdf_dim)
    archive = args.out / "upload.zip"
    zip_tree(data, archive)
    token = secrets.token_urlsafe(16)
    env = {"PROX_JOB_STALE_S": str(STALE_S), "PROX_REAP_INTERVAL_S": "2"}
    report: dict = {"jobs": args.jobs, "workers": args.workers}
    with LocalStack(args.out / "service", f"load:{token}", workers=args.workers,
                    env=env) as stack:
        client = ApiClient(stack.url, token, timeout=300)
        print(f"submitting {args.jobs} jobs at once to {stack.url} ({args.workers} workers)")

        def timed_submit(_: int) -> tuple[str, float]:
            t0 = time.perf_counter()
            job = ApiClient(stack.url, token, timeout=300).submit(archive, config="rgb",
                                                                   frames=1)
            return job["id"], time.perf_counter() - t0

        start = time.monotonic()
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            submitted = list(pool.map(timed_submit, range(args.jobs)))
        ids = [i for i, _ in submitted]
        latencies = sorted(s for _, s in submitted)
        def redis_outage() -> None:
            print(f"killing Redis (SIGKILL) for {REDIS_DOWN_S} s mid-run", flush=True)
            killed = time.monotonic()
            stack.restart_redis(down_s=REDIS_DOWN_S)
            report["redis_restarted_after_s"] = round(time.monotonic() - killed, 1)

        jobs = _wait_all(client, ids, timeout=3600, outage=redis_outage)
        wall = time.monotonic() - start
        store = JobStore(Settings(redis_url=stack.redis_url))
        runs = [store.get(i)["runs"] for i in ids]
        frames = [_check_results(client, i) for i in ids if jobs[i]["status"] == "finished"]
        listed = client.http.get("/v1/jobs", params={"limit": 100}).json()["total"]
        timed = [j["timings"] for j in jobs.values() if j["timings"]["run_seconds"]]
        report["load"] = {
            "distinct_ids": len(set(ids)), "listed": listed,
            "finished": sum(j["status"] == "finished" for j in jobs.values()),
            "failed": sum(j["status"] == "failed" for j in jobs.values()),
            "ran_more_than_once": sum(r != 1 for r in runs),
            "results_with_one_frame": sum(f == 1 for f in frames),
            "submit_seconds_median": round(statistics.median(latencies), 3),
            "submit_seconds_max": round(latencies[-1], 3),
            "wall_seconds": round(wall, 1),
            "jobs_per_minute": round(args.jobs / wall * 60, 1),
            "run_seconds_mean": round(statistics.mean(t["run_seconds"] for t in timed), 2),
            # a job's overhead: its run less the seconds its frame took to fit
            "besides_fitting_seconds_mean": round(statistics.mean(
                t["run_seconds"] - t["seconds_per_frame"] for t in timed), 2),
            "steps_seconds_mean": {step: round(statistics.mean(
                t["steps"][step] for t in timed), 3) for step in timed[0]["steps"]},
            "queued_seconds_max": round(max(j["timings"]["queued_seconds"] or 0
                                            for j in jobs.values()), 1),
        }
        print(json.dumps(report["load"], indent=1))
        print("killing a work-horse mid-job")
        report["horse_killed"] = _kill_check(client, stack, archive, whole_worker=False)
        print(json.dumps(report["horse_killed"], indent=1))
        print("killing a whole worker mid-job")
        report["worker_killed"] = _kill_check(client, stack, archive, whole_worker=True)
        print(json.dumps(report["worker_killed"], indent=1))

    load = report["load"]
    ok = (load["distinct_ids"] == load["listed"] == load["finished"] == args.jobs
          # only the jobs running when Redis was killed may run a second time
          and load["ran_more_than_once"] <= args.workers
          and load["results_with_one_frame"] == args.jobs
          and all(report[k]["status"] == "finished" and report[k]["attempt"] == 2
                  for k in ("horse_killed", "worker_killed")))
    report["ok"] = ok
    (args.out / "loadcheck.json").write_text(json.dumps(report, indent=1))
    print(f"{'OK' if ok else 'FAILED'}: figures in {args.out / 'loadcheck.json'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
