"""Two configurations' fits of the same frames side by side: per kind and overall their mean
PJE / V2V / p.PJE (mm) and penetration, and how many frames the second fits better and
worse than the first by more than a threshold (mm), with the frames that moved most. A
change's mean moves by a millimetre when a few frames move by tens, so the counts say
whether it is a few frames or many.

    .venv/bin/python -m benchmarks.compare OUT/results.json:prox OTHER/results.json:prox-soft
    .venv/bin/python -m benchmarks.compare A/results.json:prox A/results.json:prox-sequence \\
        B/results.json:prox B/results.json:prox-sequence   # pairs from several seeds
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .evaluate import aggregate

MEANS = (("pje", "PJE"), ("v2v", "V2V"), ("p_pje", "p.PJE"))


def load_rows(spec: str) -> list[dict]:
    """The frame rows of ``RESULTS.json:CONFIG`` (a ``python -m benchmarks`` output)."""
    path, _, config = spec.rpartition(":")
    try:
        frames = json.loads(Path(path).read_text())["frames"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not a `python -m benchmarks` results file ({exc!r})")
    if config not in frames:
        raise SystemExit(f"{path}: no configuration '{config}' (it has {', '.join(frames)})")
    return frames[config]


def paired(first: list[dict], second: list[dict], threshold_mm: float = 15.0) -> dict:
    """Per kind and "all": both sides' :func:`evaluate.aggregate`, and the frames the second fits
    better / worse than the first by more than ``threshold_mm`` PJE; "moved": every
    frame's (PJE change mm, kind, frame), largest gain first. Frames are matched by kind
    and name (one recording per kind and seed)."""
    second_of = {(r["kind"], r["frame"]): r for r in second}
    pairs = [(a, second_of[(a["kind"], a["frame"])]) for a in first
             if (a["kind"], a["frame"]) in second_of]
    if len(pairs) != len(first) or len(pairs) != len(second):
        raise ValueError(f"the two sides do not fit the same frames ({len(first)} and "
                         f"{len(second)} frames, {len(pairs)} in common)")
    table = {}
    for kind in [*sorted({a["kind"] for a, _ in pairs}), "all"]:
        chosen = [(a, b) for a, b in pairs if kind in ("all", a["kind"])]
        change = np.array([b["pje"] - a["pje"] for a, b in chosen])
        table[kind] = {
            **{side: aggregate([p[i] for p in chosen])
               for i, side in enumerate(("first", "second"))},
            "better": int((change < -threshold_mm).sum()),
            "worse": int((change > threshold_mm).sum()),
        }
    moved = sorted((b["pje"] - a["pje"], a["kind"], a["frame"]) for a, b in pairs)
    return {"table": table, "moved": moved}


def render(result: dict, names: tuple[str, str], threshold_mm: float, top: int = 5) -> str:
    """``paired``'s result as Markdown: one row per kind, then the frames that moved most."""
    head = " / ".join(label for _, label in MEANS)
    lines = [f"| kind | {names[0]}: {head} | {names[1]}: {head} | pen. % | "
             f"frames better / worse by > {threshold_mm:g} mm |", "|---|---|---|---|---|"]
    for kind, row in result["table"].items():
        sides = [" / ".join(f"{row[s][k]:.1f}" for k, _ in MEANS) for s in ("first", "second")]
        pen = " -> ".join(f"{100 * row[s]['penetrating_share']:.2f}" for s in ("first", "second"))
        lines.append(f"| {kind} | {sides[0]} | {sides[1]} | {pen} | "
                     f"{row['better']} / {row['worse']} |")
    moved = result["moved"]
    shown = moved[:top] + [m for m in moved[-top:] if m not in moved[:top]]
    lines += ["", "Frames that moved most (PJE change, mm):"]
    lines += [f"- {change:+.1f} {kind} {frame}" for change, kind, frame in shown]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sides", nargs="+", metavar="RESULTS.json:CONFIG",
                        help="pairs: the first configuration's fits, then the second's")
    parser.add_argument("--threshold", type=float, default=15.0, help="mm (default 15)")
    args = parser.parse_args(argv)
    if len(args.sides) % 2:
        parser.error("give the sides in pairs: FIRST SECOND [FIRST SECOND ...]")
    first, second = [], []
    for pair, (a, b) in enumerate(zip(args.sides[::2], args.sides[1::2]), 1):
        # frames named by their pair, so that several seeds' frames stay apart
        first += [{**r, "frame": f"{pair}:{r['frame']}"} for r in load_rows(a)]
        second += [{**r, "frame": f"{pair}:{r['frame']}"} for r in load_rows(b)]
    names = (args.sides[0].rpartition(":")[2], args.sides[1].rpartition(":")[2])
    try:
        result = paired(first, second, args.threshold)
    except ValueError as exc:
        parser.error(str(exc))
    print(render(result, names, args.threshold))


if __name__ == "__main__":
    main()
