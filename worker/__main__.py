"""``python -m worker``: an RQ worker on the prox queue (one per CPU core).

Each job runs in a forked work-horse, so a job that crashes or is killed takes only its
horse down; the worker reports the loss and the job is retried once or failed. The parent
loads the default body model and runs it once on one thread, imports the fit's and the
report's modules and compiles the report's templates before it forks (every horse
inherits them warm, so no job pays for loading them), and never renders (a forked
child's OpenGL context hangs; see docs/service.md).
"""
from __future__ import annotations

import argparse
import logging
import os
import secrets
import socket
import sys
import time

from redis import Redis
from redis.exceptions import ConnectionError as RedisConnectionError
from rq import Worker

from service.jobs import JobStore
from service.settings import Settings
from worker.tasks import clean_scratch, preload

# A worker that stops heart-beating drops out of /healthz after this long.
WORKER_TTL_S = 60
MAX_WAIT_S = 30  # the longest pause between attempts to reach Redis again


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m worker", description=__doc__)
    parser.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    parser.add_argument("--max-jobs", type=int, help="exit after this many jobs (recycling)")
    parser.add_argument("--name", help="worker name, followed by the pid and a random "
                                       "suffix (default: the host name)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s worker %(message)s")
    settings = Settings.from_env()
    store = JobStore(settings)

    def horse_killed(job, retpid: int, ret_val: int, rusage) -> None:
        job_id, attempt = job.args
        how = (f"signal {os.WTERMSIG(ret_val)}" if os.WIFSIGNALED(ret_val)
               else f"exit status {os.waitstatus_to_exitcode(ret_val)}")
        store.worker_lost(job_id, attempt, f"its worker process died ({how})")
        clean_scratch(store, job_id)

    logging.info("body model loaded and warmed in %.1f s", preload())

    try:
        for folder in clean_scratch(store):
            logging.info("removed %s, left by a killed work-horse", folder)
    except RedisConnectionError as exc:  # cleaned at the next start instead
        logging.warning("Redis unreachable (%s): scratch folders not checked", exc)

    wait = 1.0
    while True:  # ride out Redis outages: a busy RQ worker dies when Redis drops
        # A fresh name each time: Redis refuses one whose last owner has not expired.
        name = f"{args.name or socket.gethostname()}-{os.getpid()}-{secrets.token_hex(3)}"
        try:
            worker = Worker([settings.queue], name=name,
                            connection=Redis.from_url(settings.redis_url),
                            worker_ttl=WORKER_TTL_S, work_horse_killed_handler=horse_killed)
            worker.work(burst=args.burst, max_jobs=args.max_jobs, logging_level="INFO")
            return 0
        except RedisConnectionError as exc:
            logging.warning("Redis unreachable (%s); starting again in %.0f s", exc, wait)
            time.sleep(wait)
            wait = min(2 * wait, MAX_WAIT_S)


if __name__ == "__main__":
    sys.exit(main())
