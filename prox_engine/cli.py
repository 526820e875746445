"""``prox``: command line for one machine, on the same engine as the workers."""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import textwrap
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from .config import BODY_MODELS, CONFIG_DIR, GENDERS
from .errors import InputError

if TYPE_CHECKING:
    from .config import FitConfig


def _threads() -> None:
    import torch

    # One thread per fitting process: a second thread gains little and collapses when
    # another process holds a core (see README, Performance).
    torch.set_num_threads(int(os.environ.get("PROX_THREADS", "1")))


def cmd_setup(args: argparse.Namespace) -> int:
    from . import assets

    start = time.perf_counter()
    path = assets.setup(force=args.force, say=lambda text: print(text, flush=True))
    print(f"anny model data: {path} ({time.perf_counter() - start:.1f} s)")
    return 0


def cmd_fit(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .body import load_body
    from .dataset import list_recordings
    from .pipeline import fit_recording

    _threads()
    config = _config_with_body(args)
    if args.batch is not None:
        config = dataclasses.replace(config, batch_size=args.batch)
    recordings = args.recording or list_recordings(args.base)
    genders = _genders(args.genders) if args.genders else {}
    bodies: dict[str, object] = {}
    failed = False
    rows = []
    for name in recordings:
        gender = genders.get(name, config.gender)
        if gender not in bodies:
            bodies[gender] = load_body(config, gender)
        body = bodies[gender]
        bar = tqdm(total=None, desc=name, unit="frame", file=sys.stderr,
                   disable=not sys.stderr.isatty() and not args.progress)

        def progress(done: int, total: int, frame: str) -> None:
            bar.total = total
            bar.n = done
            bar.set_postfix_str(frame)  # whole: frame names differ at their ends
            bar.refresh()

        try:
            result = fit_recording(args.base, name, args.out, config, body,
                                   max_frames=args.frames, sequence=args.sequence,
                                   progress=progress)
        except InputError as exc:
            bar.close()
            print(f"error: {exc}", file=sys.stderr)
            failed = True
            continue
        bar.close()
        for frame, error in result.failures:
            print(f"skipped {frame}: {error}", file=sys.stderr)
        for event in result.summary["numerical_events"]:
            print(f"warning {event['frame']}: {event['event']}", file=sys.stderr)
        registration = result.summary["registration"]
        if registration["failed"]:
            print(f"warning {name}: scan registration kept as given "
                  f"({registration['reason']})", file=sys.stderr)
        if not result.summary["frames_fitted"]:
            print(f"error: {name}: no frame could be fitted", file=sys.stderr)
            failed = True
        rows.append(result.summary)
    if rows:
        _print_summary(rows, config.name, args.sequence, Path(args.out))
    if rows and not args.no_report:
        from .report import build_report, write_index

        for row in rows:
            if row["frames_fitted"]:
                build_report(Path(args.out) / row["recording"], every=args.render_every)
        print(f"reports: {write_index(args.out, recordings, f'prox fit {args.base}')}")
    return 1 if failed or not rows else 0


def _config_with_body(args: argparse.Namespace) -> FitConfig:
    """The configuration with the body-model options of the command line applied."""
    from .config import load_config

    options = {"model": args.model, "model_path": args.model_path, "gender": args.gender,
               "hand_pca": args.hand_pca, "body_segments": args.body_segments,
               "vposer_path": args.vposer_path}
    return dataclasses.replace(load_config(args.config, args.model or "anny"),
                               **{k: v for k, v in options.items() if v is not None})


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: give 1 or more")
    return value


def _genders(path: Path) -> dict[str, str]:
    """A per-recording gender map: a JSON object {"<recording>": "male", ...}."""
    try:
        genders = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read the gender map ({exc})") from exc
    if not isinstance(genders, dict) or not all(g in GENDERS for g in genders.values()):
        raise InputError(path, 'expected {"<recording>": "neutral" | "male" | "female", ...}')
    return genders


def _print_summary(rows: list[dict], config: str, sequence: bool, out: Path) -> None:
    mode = "sequence" if sequence else "single-frame"
    print(f"\nconfig {config} ({mode}); results in {out}")
    header = f"{'recording':<28} {'frames':>6} {'failed':>6} {'s/frame':>8} " \
             f"{'reproj px':>9} {'pen %':>6} {'max pen cm':>10} {'contact %':>9}"
    print(header)
    print("-" * len(header))
    for s in rows:
        fmt = lambda v, f: format(v, f) if v is not None else "-"  # noqa: E731
        pen = s["penetration"]
        share = pen["mean_penetrating_share"]
        contact = s["contact"]["share_of_frames_with_contact"]
        print(f"{s['recording']:<28} {s['frames_fitted']:>6} {s['frames_failed']:>6} "
              f"{fmt(s['seconds_per_frame'], '8.2f')} {fmt(s['reprojection_error_px'], '9.1f')} "
              f"{fmt(share * 100 if share is not None else None, '6.2f')} "
              f"{fmt(pen['max_depth_m'] * 100 if pen['max_depth_m'] is not None else None, '10.1f')} "
              f"{fmt(contact * 100 if contact is not None else None, '9.0f')}")


def cmd_demo(args: argparse.Namespace) -> int:
    """Generate the synthetic sitting scene and fit it with rgb and prox through a local
    service: real HTTP upload, queue, workers and download."""
    import secrets

    from service.client import ApiClient
    from service.local import LocalStack
    from service.storage import zip_tree

    from .synthetic import make_sitting_dataset

    out = Path(args.out)
    data = make_sitting_dataset(out / "data", frames=args.frames)
    archive = out / "upload.zip"
    zip_tree(data, archive)
    token = secrets.token_urlsafe(16)
    rows = {}
    with LocalStack(out / "service", f"demo:{token}", workers=2) as stack:
        print(f"service running at {stack.url} (API docs: {stack.url}/docs)")
        client = ApiClient(stack.url, token)
        jobs = {name: client.submit(archive, config=name) for name in ("rgb", "prox")}
        for name, job in jobs.items():
            print(f"submitted {archive} as job {job['id']} (config {name})")
        show = _progress_printer()
        for name, job in jobs.items():
            final = client.wait(job["id"], on_update=show)
            if final["status"] != "finished":
                print(f"job {job['id']} {final['status']}: {final['error']}", file=sys.stderr)
                return 1
            client.download(job["id"], out / name)
            summary = json.loads((out / name / "Synthetic_00000_01" / "summary.json")
                                 .read_text())
            rows[name] = summary
            _print_summary([summary], name, False, out / name)
    from .report import build_report

    report = build_report(out / "prox" / "Synthetic_00000_01", data=data,
                          baseline=out / "rgb" / "Synthetic_00000_01")
    print("\n" + json.dumps({k: {"penetrating_share": v["penetration"]["mean_penetrating_share"],
                                 "seconds_per_frame": v["seconds_per_frame"]}
                             for k, v in rows.items()}, indent=1))
    print(f"\nresults downloaded to {out / 'rgb'} and {out / 'prox'} "
          f"(service logs in {out / 'service' / 'logs'})")
    print(f"report: {report} (comparison: {report.parent / 'compare.html'})")
    return 0


def _progress_printer() -> Callable[[dict], None]:
    """Prints a job's status line each time it changes."""
    last: dict[str, str] = {}

    def show(job: dict) -> None:
        p = job["progress"]
        line = (f"  job {job['id'][:8]} {job['config']:>4}: {job['status']:<9} "
                f"{p['frames_done']}/{p['frames_total']} frames  {p['stage'] or ''}")
        if last.get(job["id"]) != line:
            last[job["id"]] = line
            print(line, flush=True)

    return show


def cmd_report(args: argparse.Namespace) -> int:
    """(Re)build the HTML report of fitted results."""
    from .report import build_report

    start = time.perf_counter()
    index = build_report(args.results, data=args.data, baseline=args.compare,
                         every=args.every, flags=not args.no_flags)
    timings = json.loads((index.parent / "timings.json").read_text())
    print(f"report: {index} ({timings['frames_rendered']} frames rendered, "
          f"{timings['seconds_per_frame']:.2f} s per frame for its views, "
          f"{time.perf_counter() - start:.1f} s in all)")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    """Redis (unless one is configured), the API and workers on this machine."""
    import secrets
    import signal

    from service.local import LocalStack

    token = None
    tokens = os.environ.get("PROX_API_TOKENS")
    if not tokens and not os.environ.get("PROX_TOKENS_FILE"):
        token = args.token or secrets.token_urlsafe(16)
        tokens = f"local:{token}"
    from .assets import home

    stack = LocalStack(args.root or home() / "service", tokens or "", workers=args.workers,
                       port=args.port,
                       redis_url=args.redis_url or os.environ.get("PROX_REDIS_URL"),
                       env={k: os.environ[k] for k in ("PROX_STORAGE_DIR",)
                            if k in os.environ})
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # stop cleanly on SIGTERM
    with stack:
        print(f"prox service at {stack.url} (API docs {stack.url}/docs), "
              f"{args.workers} worker(s), Redis {stack.redis_url}, files in {stack.root}")
        if token:
            print(f"API token: {token}   (curl -H 'Authorization: Bearer {token}' "
                  f"{stack.url}/v1/jobs)")
        print("Ctrl-C stops it.", flush=True)
        try:
            while stack.api.poll() is None:
                for name in stack.supervise():
                    print(f"{name} exited and was restarted; see the logs in "
                          f"{stack.root / 'logs'}", file=sys.stderr, flush=True)
                time.sleep(1)
            print(f"the API exited; see the logs in {stack.root / 'logs'}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            return 0


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's, but a line never breaks inside a hyphenated configuration name."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="prox", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("setup", help="bake the body model and warm caches (once)")
    p.add_argument("--force", action="store_true", help="rebuild even if present")
    p.set_defaults(func=cmd_setup)

    p = sub.add_parser("fit", help="fit recordings of a PROX-layout directory",
                       formatter_class=_HelpFormatter)
    p.add_argument("base", type=Path, help="PROX-layout base directory")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--recording", action="append", help="recording name (repeatable); "
                   "default: every folder under BASE/keypoints")
    builtin = " | ".join(sorted(path.stem for path in CONFIG_DIR.glob("*.yaml")))
    p.add_argument("--config", default="prox",
                   help=f"{builtin} | FILE.yaml (default prox)")
    p.add_argument("--frames", type=int, help="fit only the first N frames")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--sequence", action="store_true",
                      help="warm-start each frame from the previous fit (with prox, "
                           "also fit it from scratch and keep, frame by frame, the fit "
                           "on the path along which the body moves least)")
    mode.add_argument("--batch", type=_positive, metavar="N",
                      help="fit N frames of a recording together (default: the "
                           "configuration's batch_size, 1)")
    p.add_argument("--progress", action="store_true", help="progress bar even when not a tty")
    p.add_argument("--model", choices=BODY_MODELS,
                   help="body model (default: the configuration's, anny)")
    p.add_argument("--model-path", help="folder with your licensed SMPLX_{NEUTRAL,MALE,"
                   "FEMALE}.npz (never downloaded)")
    p.add_argument("--gender", choices=GENDERS)
    p.add_argument("--genders", type=Path, metavar="FILE.json",
                   help='per-recording genders {"<recording>": "female", ...}')
    p.add_argument("--hand-pca", type=int, metavar="N",
                   help="SMPL-X hand PCA components (default 12; 0: every finger joint)")
    p.add_argument("--body-segments", metavar="DIR",
                   help="PROX's body_segments/ folder: its contact vertices for SMPL-X")
    p.add_argument("--vposer-path", metavar="PATH",
                   help="your VPoser v1.0 snapshot (.pt) or its folder: SMPL-X's pose prior")
    p.add_argument("--no-report", action="store_true", help="skip the HTML reports")
    p.add_argument("--render-every", type=int, default=1, metavar="K",
                   help="render every k-th frame in the reports")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("report", help="(re)build the HTML report of a fitted recording")
    p.add_argument("results", type=Path, help="OUT/<rec>: one recording's results")
    p.add_argument("--data", type=Path, help="the PROX-layout input that was fitted "
                   "(default: the path in summary.json)")
    p.add_argument("--compare", type=Path, metavar="OTHER/<rec>",
                   help="results of another configuration (the baseline, drawn in yellow)")
    p.add_argument("--every", type=int, default=1, help="render every k-th frame")
    p.add_argument("--no-flags", action="store_true",
                   help="do not paint penetrating (red) and contact (blue) vertices")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("demo", help="synthetic sitting scene, fitted with rgb and prox "
                                    "through a local service")
    p.add_argument("--out", type=Path, default=Path("demo_output"))
    p.add_argument("--frames", type=int, default=2)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("serve", help="run Redis, the API and workers on this machine")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1, help="worker processes (one per core)")
    p.add_argument("--root", type=Path, default=None,
                   help="job files and logs (default $PROX_HOME/service)")
    p.add_argument("--redis-url", help="use this Redis instead of starting one")
    p.add_argument("--token", help="API token when PROX_API_TOKENS is not set "
                                   "(default: a random one, printed)")
    p.set_defaults(func=cmd_serve)

    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
