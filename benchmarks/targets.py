"""Issue 11's targets checked on held-out seeds, pooled and seed by seed, from the results
files of ``python -m benchmarks`` runs (a seed's configurations may be split over several
files, as when single frames and sequence mode run in two processes):

- single frames' PJE at most PJE_MAX mm and p.PJE at most P_PJE_MAX;
- single frames' PJE cut by at least CUT_MIN against the baseline's;
- at most PENETRATION_MAX of the vertices more than 1 cm inside the true scan;
- every kind nearer the truth than the baseline in PJE and V2V, in both modes;
- sequence mode's PJE no worse than single frames'.

Besides the pooled and per-seed tables: each kind, each detector condition, and sequence
mode against single frames by recording (the mean difference and a bootstrap interval:
frames of one recording are not independent draws).

    .venv/bin/python -m benchmarks.targets OUT196/a/results.json OUT196/b/results.json \\
        OUT197/a/results.json OUT197/b/results.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import textwrap
from pathlib import Path

import numpy as np

from .evaluate import CONDITIONS, aggregate

PJE_MAX, P_PJE_MAX, CUT_MIN, PENETRATION_MAX = 100.0, 60.0, 0.30, 0.005
MOVED_MM = 15.0  # frames that moved by more than this are counted
WIDTH = 90  # the report's paragraphs wrapped as the README's prose


def load(paths: list[Path]) -> dict[int, dict[str, list[dict]]]:
    """Frame rows by seed and configuration, from ``python -m benchmarks`` results files."""
    by_seed: dict[int, dict[str, list[dict]]] = {}
    for path in paths:
        try:
            result = json.loads(Path(path).read_text())
            seed, frames = int(result["settings"]["seed"]), result["frames"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"{path}: not a `python -m benchmarks` results file ({exc!r})")
        configs = by_seed.setdefault(seed, {})
        for config, rows in frames.items():
            if config in configs:
                raise SystemExit(f"{path}: seed {seed}'s '{config}' is in another file too")
            configs[config] = [{**row, "seed": seed} for row in rows]
    return by_seed


def pooled(by_seed: dict[int, dict[str, list[dict]]]) -> dict[str, list[dict]]:
    """Every seed's rows of each configuration together."""
    rows: dict[str, list[dict]] = {}
    for configs in by_seed.values():
        for config, frames in configs.items():
            rows.setdefault(config, []).extend(frames)
    return rows


def missed(rows: dict[str, list[dict]], baseline: str, single: str,
           sequence: str | None) -> list[str]:
    """The targets (module docstring) that ``rows`` (configuration -> frame rows) miss,
    each with its figures; none: every target holds."""
    base, fit = aggregate(rows[baseline]), aggregate(rows[single])
    misses = []
    if fit["pje"] > PJE_MAX:
        misses.append(f"PJE {fit['pje']:.1f}")
    if fit["p_pje"] > P_PJE_MAX:
        misses.append(f"p.PJE {fit['p_pje']:.1f}")
    if fit["pje"] > (1 - CUT_MIN) * base["pje"]:
        misses.append(f"PJE cut {100 * (1 - fit['pje'] / base['pje']):.0f} %")
    modes = [("single frames", single)] + ([("sequence mode", sequence)] if sequence else [])
    overall = {config: aggregate(rows[config]) for _, config in modes}
    for mode, config in modes:
        share = overall[config]["penetrating_share"]
        if share > PENETRATION_MAX:
            misses.append(f"penetration {100 * share:.2f} % in {mode}")
    for kind in sorted({r["kind"] for r in rows[baseline]}):
        ref = aggregate([r for r in rows[baseline] if r["kind"] == kind])
        for mode, config in modes:
            got = aggregate([r for r in rows[config] if r["kind"] == kind])
            lost = [name for key, name in (("pje", "PJE"), ("v2v", "V2V"))
                    if got[key] >= ref[key]]
            if lost:
                misses.append(f"{kind} in {' and '.join(lost)} in {mode} ({got['pje']:.1f} / "
                              f"{got['v2v']:.1f} against {ref['pje']:.1f} / {ref['v2v']:.1f})")
    if sequence and overall[sequence]["pje"] > fit["pje"]:
        misses.append(f"sequence mode worse ({overall[sequence]['pje']:.1f})")
    return misses


def by_recording(first: list[dict], second: list[dict], draws: int = 4000
                 ) -> tuple[float, float, float]:
    """The mean over recordings (a seed's kind) of ``second``'s PJE less ``first``'s, and
    its 95 % bootstrap interval over recordings (seeded: the same files, the same
    interval)."""
    def means(rows: list[dict]) -> dict[tuple, float]:
        per: dict[tuple, list[float]] = {}
        for r in rows:
            per.setdefault((r["seed"], r["kind"]), []).append(r["pje"])
        return {k: statistics.fmean(v) for k, v in per.items()}

    a, b = means(first), means(second)
    if a.keys() != b.keys():
        raise SystemExit("the two configurations do not cover the same recordings")
    diffs = np.array([b[k] - a[k] for k in sorted(a)])
    draws_of = np.random.default_rng(0).integers(0, len(diffs), (draws, len(diffs)))
    low, high = np.percentile(diffs[draws_of].mean(1), [2.5, 97.5])
    return float(diffs.mean()), float(low), float(high)


def report(by_seed: dict[int, dict[str, list[dict]]], baseline: str = "rgb",
           single: str = "prox", sequence: str | None = "prox-sequence") -> str:
    """The held-out seeds' tables as Markdown (see the module docstring)."""
    rows = pooled(by_seed)
    for config in (baseline, single, sequence):
        if config and config not in rows:
            raise SystemExit(f"no configuration '{config}' in the files (they have "
                             f"{', '.join(rows)})")
    modes = [c for c in (baseline, single, sequence) if c]
    for seed, configs in by_seed.items():
        lacking = [c for c in modes if c not in configs]
        if lacking:
            raise SystemExit(f"seed {seed} has no '{', '.join(lacking)}' in the files")
    lines = ["| config | PJE | p.PJE | V2V | pen. % | sides |", "|---|---|---|---|---|---|"]
    for config, frames in rows.items():
        m = aggregate(frames)
        lines.append(f"| {config} | {m['pje']:.1f} | {m['p_pje']:.1f} | {m['v2v']:.1f} | "
                     f"{100 * m['penetrating_share']:.2f} | "
                     f"{sum(bool(r['sides_right']) for r in frames)} / {len(frames)} |")
    lines += ["", "| kind (PJE / V2V mm) | " + " | ".join(modes) + " |",
              "|---" * (len(modes) + 1) + "|"]
    for kind in sorted({r["kind"] for r in rows[baseline]}):
        cells = [aggregate([r for r in rows[c] if r["kind"] == kind]) for c in modes]
        lines.append(f"| {kind} | " + " | ".join(f"{m['pje']:.1f} / {m['v2v']:.1f}"
                                                 for m in cells) + " |")
    lines += ["", f"| seed | {baseline} PJE | {single} PJE / p.PJE | "
              + (f"{sequence} PJE | " if sequence else "")
              + "pen. % | median / worst frame | targets missed |",
              "|---" * (7 if sequence else 6) + "|"]
    misses = {seed: missed(configs, baseline, single, sequence)
              for seed, configs in sorted(by_seed.items())}
    for seed, configs in sorted(by_seed.items()):
        fit = aggregate(configs[single])
        errors = sorted(r["pje"] for r in configs[single])
        lines.append(
            f"| {seed} | {aggregate(configs[baseline])['pje']:.1f} | {fit['pje']:.1f} / "
            f"{fit['p_pje']:.1f} | "
            + (f"{aggregate(configs[sequence])['pje']:.1f} | " if sequence else "")
            + f"{100 * fit['penetrating_share']:.2f} | {statistics.median(errors):.1f} / "
            f"{errors[-1]:.0f} | {'; '.join(misses[seed]) or 'none'} |")
    held = [seed for seed, missing in misses.items() if not missing]
    lines += ["", _wrapped(f"Pooled, targets missed: "
                           f"{'; '.join(missed(rows, baseline, single, sequence)) or 'none'}. "
                           f"Every target held on {len(held)} of {len(by_seed)} seeds"
                           + (f" ({', '.join(map(str, sorted(held)))})." if held else "."))]
    lines += ["", f"| condition | frames | {single} PJE / p.PJE | {baseline} PJE | "
              + (f"{sequence} PJE |" if sequence else ""),
              "|---" * (5 if sequence else 4) + "|"]
    for condition in CONDITIONS:
        cells = {c: [r for r in rows[c] if r["condition"] == condition] for c in modes}
        if not cells[single]:
            continue
        fit = aggregate(cells[single])
        lines.append(f"| {condition} | {len(cells[single])} | {fit['pje']:.1f} / "
                     f"{fit['p_pje']:.1f} | {aggregate(cells[baseline])['pje']:.1f} | "
                     + (f"{aggregate(cells[sequence])['pje']:.1f} |" if sequence else ""))
    errors = [r["pje"] for r in rows[single]]
    summary = (f"{single}: median frame {statistics.median(errors):.1f} mm, "
               f"{sum(e > 200 for e in errors)} of {len(errors)} over 200, "
               f"{sum(e > 300 for e in errors)} over 300.")
    if sequence:
        mean, low, high = by_recording(rows[single], rows[sequence])
        change = {(r["seed"], r["kind"], r["frame"]): r["pje"] for r in rows[single]}
        moved = [r["pje"] - change[(r["seed"], r["kind"], r["frame"])] for r in rows[sequence]]
        summary += (f" {sequence} against {single}, by recording: {mean:+.2f} mm (95 % "
                    f"{low:+.2f} to {high:+.2f}); frames better / worse by more than "
                    f"{MOVED_MM:g} mm: {sum(m < -MOVED_MM for m in moved)} / "
                    f"{sum(m > MOVED_MM for m in moved)}.")
    return "\n".join([*lines, "", _wrapped(summary)])


def _wrapped(text: str) -> str:
    """A paragraph of the report, wrapped as the README's prose is."""
    return textwrap.fill(text, WIDTH, break_on_hyphens=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", type=Path, metavar="RESULTS.json")
    parser.add_argument("--baseline", default="rgb")
    parser.add_argument("--single", default="prox")
    parser.add_argument("--sequence", default="prox-sequence",
                        help="sequence mode's configuration ('' for none)")
    args = parser.parse_args(argv)
    print(report(load(args.results), args.baseline, args.single, args.sequence or None))


if __name__ == "__main__":
    main()
