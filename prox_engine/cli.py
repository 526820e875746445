"""``prox``: command line for one machine, on the same engine as the workers."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from .errors import InputError


def _threads() -> None:
    import torch

    # One thread per fitting process: a second thread gains little and collapses when
    # another process holds a core (see README, Performance).
    torch.set_num_threads(int(os.environ.get("PROX_THREADS", "1")))


def cmd_setup(args: argparse.Namespace) -> int:
    from . import assets

    start = time.perf_counter()
    path = assets.setup(force=args.force)
    print(f"anny model data: {path} ({time.perf_counter() - start:.1f} s)")
    return 0


def cmd_fit(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .body.anny_body import AnnyBody
    from .config import load_config
    from .dataset import list_recordings
    from .pipeline import fit_recording

    _threads()
    config = load_config(args.config)
    recordings = args.recording or list_recordings(args.base)
    body = AnnyBody.load()
    failed = False
    rows = []
    for name in recordings:
        bar = tqdm(total=None, desc=name, unit="frame", file=sys.stderr,
                   disable=not sys.stderr.isatty() and not args.progress)

        def progress(done: int, total: int, frame: str) -> None:
            bar.total = total
            bar.n = done
            bar.set_postfix_str(frame[-24:])
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
        rows.append(result.summary)
    _print_summary(rows, config.name, args.sequence, Path(args.out))
    return 1 if failed or not rows else 0


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
    """Generate the synthetic sitting scene and fit it with rgb and prox."""
    from .body.anny_body import AnnyBody
    from .config import load_config
    from .pipeline import fit_recording
    from .synthetic import make_sitting_dataset

    _threads()
    out = Path(args.out)
    body = AnnyBody.load()
    data = make_sitting_dataset(out / "data", frames=args.frames, body=body)
    rows = {}
    for name in ("rgb", "prox"):
        config = load_config(name)
        result = fit_recording(data, "Synthetic_00000_01", out / name, config, body)
        rows[name] = result.summary
        _print_summary([result.summary], name, False, out / name)
    print("\n" + json.dumps({k: {"penetrating_share": v["penetration"]["mean_penetrating_share"],
                                 "seconds_per_frame": v["seconds_per_frame"]}
                             for k, v in rows.items()}, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="prox", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("setup", help="bake the body model and warm caches (once)")
    p.add_argument("--force", action="store_true", help="rebuild even if present")
    p.set_defaults(func=cmd_setup)

    p = sub.add_parser("fit", help="fit recordings of a PROX-layout directory")
    p.add_argument("base", type=Path, help="PROX-layout base directory")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--recording", action="append", help="recording name (repeatable); "
                   "default: every folder under BASE/keypoints")
    p.add_argument("--config", default="prox",
                   help="rgb | prox | smplifyd | proxd | FILE.yaml (default prox)")
    p.add_argument("--frames", type=int, help="fit only the first N frames")
    p.add_argument("--sequence", action="store_true",
                   help="warm-start each frame from the previous fit")
    p.add_argument("--progress", action="store_true", help="progress bar even when not a tty")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("demo", help="synthetic sitting scene, fitted with rgb and prox")
    p.add_argument("--out", type=Path, default=Path("demo_output"))
    p.add_argument("--frames", type=int, default=2)
    p.set_defaults(func=cmd_demo)

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
