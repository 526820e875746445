"""A small Python client of the job API (used by ``prox demo`` and the load check)."""
from __future__ import annotations

import time
import zipfile
from pathlib import Path
from typing import Callable

import httpx


class ApiClient:
    def __init__(self, url: str, token: str, timeout: float = 60.0) -> None:
        self.http = httpx.Client(base_url=url, timeout=timeout,
                                 headers={"Authorization": f"Bearer {token}"})

    def submit(self, archive: Path, config: str = "prox", frames: int | None = None,
               sequence: bool = False) -> dict:
        """Upload a zip in the PROX layout; the new job's status."""
        data = {"config": config, "sequence": str(sequence).lower()}
        if frames is not None:
            data["frames"] = str(frames)
        with Path(archive).open("rb") as handle:
            answer = self.http.post("/v1/jobs", data=data,
                                    files={"file": (Path(archive).name, handle,
                                                    "application/zip")})
        return self._json(answer)

    def job(self, job_id: str, patience: float = 120.0) -> dict:
        """The job's status; while the service answers 503 (its job store down), ask again
        after its Retry-After, for up to ``patience`` seconds."""
        deadline = time.monotonic() + patience
        while True:
            answer = self.http.get(f"/v1/jobs/{job_id}")
            if answer.status_code != 503 or time.monotonic() > deadline:
                return self._json(answer)
            time.sleep(float(answer.headers.get("retry-after", "1")))

    def wait(self, job_id: str, timeout: float = 3600.0, poll: float = 1.0,
             on_update: Callable[[dict], None] | None = None) -> dict:
        """Poll until the job is finished, failed or cancelled."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if on_update:
                on_update(job)
            if job["status"] in ("finished", "failed", "cancelled"):
                return job
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['status']} after {timeout} s")
            time.sleep(poll)

    def download(self, job_id: str, dest: Path) -> Path:
        """Download the results zip and unpack it into ``dest``."""
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        archive = dest / f"prox-{job_id}.zip"
        with self.http.stream("GET", f"/v1/jobs/{job_id}/results") as answer:
            if answer.status_code != 200:
                answer.read()
                self._json(answer)
            with archive.open("wb") as handle:
                for chunk in answer.iter_bytes():
                    handle.write(chunk)
        with zipfile.ZipFile(archive) as zf:
            zf.extractall(dest)  # our own server's archive of plain relative paths
        return dest

    @staticmethod
    def _json(answer: httpx.Response) -> dict:
        if answer.status_code >= 400:
            raise RuntimeError(f"HTTP {answer.status_code}: {answer.text}")
        return answer.json()
