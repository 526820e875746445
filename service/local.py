"""A whole service on one machine: Redis (started if none is given), the API and N workers,
as child processes. Used by ``prox serve``, ``prox demo``, the tests and the load check."""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _stop(process: subprocess.Popen, sig: int = signal.SIGTERM, wait: float = 10.0) -> None:
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(wait)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


class LocalStack:
    """Starts on ``__enter__`` (or :meth:`start`), stops everything on exit."""

    def __init__(self, root: Path, tokens: str, workers: int = 1, port: int | None = None,
                 redis_url: str | None = None, env: dict[str, str] | None = None) -> None:
        self.root = Path(root)
        self.tokens, self.worker_count, self.redis_url = tokens, workers, redis_url
        self.port = port or free_port()
        self.extra_env = env or {}
        self.redis: subprocess.Popen | None = None
        self.redis_port: int | None = None
        self.api: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def storage_dir(self) -> Path:
        return self.root / "storage"

    def __enter__(self) -> LocalStack:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self, timeout: float = 60.0) -> None:
        (self.root / "logs").mkdir(parents=True, exist_ok=True)
        try:
            if self.redis_url is None:
                self._start_redis()
            self.api = self._spawn("api", [sys.executable, "-m", "uvicorn", "service.app:app",
                                           "--host", "127.0.0.1", "--port", str(self.port),
                                           "--log-level", "warning"], self._service_env())
            for _ in range(self.worker_count):
                self.add_worker()
            self._wait_healthy(timeout)
        except BaseException:
            self.stop()
            raise

    def add_worker(self, slot: int | None = None) -> subprocess.Popen:
        """Start a worker in ``slot`` of :attr:`workers` (replacing what was there; the
        worker makes its name fresh, which Redis requires of a restarted one)."""
        slot = len(self.workers) if slot is None else slot
        worker = self._spawn(f"worker-{slot}", [
            sys.executable, "-m", "worker", "--name", f"worker-{slot}-{self.port}"],
            self._service_env())
        if slot == len(self.workers):
            self.workers.append(worker)
        else:
            self.workers[slot] = worker
        return worker

    def supervise(self) -> list[str]:
        """Restart whatever of Redis (same port and data) and the workers has exited;
        returns what was restarted. The API is not restarted: its exit ends the stack."""
        restarted = []
        if self.redis is not None and self.redis.poll() is not None:
            self._start_redis()
            restarted.append("redis")
        for slot, worker in enumerate(self.workers):
            if worker.poll() is not None:
                self.add_worker(slot)
                restarted.append(f"worker-{slot}")
        return restarted

    def stop(self) -> None:
        """Workers first (a warm shutdown lets a running frame end), then API, then Redis."""
        for worker in self.workers:
            if worker.poll() is None:
                worker.send_signal(signal.SIGTERM)
                worker.send_signal(signal.SIGTERM)  # twice: cold shutdown, do not wait
        for process in [*self.workers, self.api, self.redis]:
            if process is not None:
                _stop(process)

    def log(self, name: str) -> str:
        path = self.root / "logs" / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def _service_env(self) -> dict[str, str]:
        """The environment of the API and the workers: this stack's Redis and files."""
        return {**os.environ, "PROX_REDIS_URL": self.redis_url,
                "PROX_STORAGE_DIR": str(self.storage_dir), "PROX_API_TOKENS": self.tokens,
                **self.extra_env}

    def _spawn(self, name: str, argv: list[str], env: dict[str, str] | None = None
               ) -> subprocess.Popen:
        with (self.root / "logs" / f"{name}.log").open("ab") as log:  # the child keeps a copy
            return subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT,
                                    cwd=Path(__file__).parents[1])

    def _start_redis(self) -> None:
        server = shutil.which("redis-server")
        if server is None:
            raise RuntimeError("redis-server not found: install Debian's redis-server "
                               "(`make setup` does) or give a Redis URL (PROX_REDIS_URL)")
        port = self.redis_port or free_port()
        data = self.root / "redis"
        data.mkdir(parents=True, exist_ok=True)
        # Append-only persistence, as in docker/compose.yaml: a restarted Redis still has
        # every job record and queued job.
        self.redis = self._spawn("redis", [server, "--port", str(port), "--bind", "127.0.0.1",
                                           "--save", "", "--appendonly", "yes",
                                           "--appendfsync", "everysec", "--dir", str(data)])
        self.redis_port = port
        self.redis_url = f"redis://127.0.0.1:{port}/0"

    def restart_redis(self, down_s: float = 0.0) -> None:
        """Kill this stack's Redis (SIGKILL: no goodbye) and start it again on the same port
        and data after ``down_s`` seconds (the load check's outage)."""
        if self.redis is None:
            raise RuntimeError("this stack uses an external Redis")
        _stop(self.redis, signal.SIGKILL)
        time.sleep(down_s)
        self._start_redis()

    def _wait_healthy(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        last = "no answer"
        while time.monotonic() < deadline:
            for name, process in [("api", self.api), ("redis", self.redis)]:
                if process is not None and process.poll() is not None:
                    raise RuntimeError(f"{name} exited at start-up:\n{self.log(name)[-2000:]}")
            try:
                answer = httpx.get(f"{self.url}/healthz", timeout=2)
                if answer.status_code == 200 and (answer.json()["workers"]
                                                  >= self.worker_count):
                    return
                last = answer.text
            except httpx.HTTPError as exc:
                last = str(exc)
            time.sleep(0.2)
        raise RuntimeError(f"service not healthy after {timeout:.0f} s ({last})")
