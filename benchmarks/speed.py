"""Where the time goes: per configuration and mode (single-frame, sequence, batched), the
seconds and body-model evaluations per frame, and the seconds per frame divided by the time
of one body forward+backward measured on the same machine in the same run (a ratio that
moves far less between machines than seconds do, though not nothing: single frames 55 on
one CPU, 63-66 on another 1.6 times slower), with the accuracy (PJE) to show nothing was
lost. A shared machine's speed drifts by a third within a minute, so the unit is measured
before and after each recording's fit, and each fit is divided by the mean of the two; the modes
are fitted in turn, recording by recording, and with ``--rounds`` each recording several
times, its seconds the median (batches' throughput against single frames is also given
round by round). In sequence mode also the seconds of the frames fitted from their
neighbour alone: what a long recording costs per frame, once its anchor frame's full fit is
spread over many frames. With several batch sizes (``--batch 2 4 8``), batches' throughput
against N, and the two costs it splits into: per frame and per batch (see
:func:`batch_costs`).

    .venv/bin/python -m benchmarks.speed --seed 1 --frames 8 --kinds sit walk --batch 8
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from prox_engine.body.anny_body import AnnyBody
from prox_engine.config import load_config
from prox_engine.output import atomic_write_text
from prox_engine.dataset import Recording
from prox_engine.pipeline import fit_recording, load_scene

from .evaluate import aggregate, evaluate_recording, truth_meta, truth_scene
from .generate import KINDS, make_benchmark


def body_seconds(body: AnnyBody, free_shape: bool, repeats: int = 30) -> float:
    """Median seconds of one forward+backward of a single body with its pose (and shape)
    free, as the fitter's stages evaluate it."""
    params = body.init_params(1)
    free = ["transl", "global_orient", *body.pose_group()]
    free += body.shape_group() if free_shape else []
    for name in free:
        params[name].requires_grad_(True)
    times = []
    for _ in range(repeats + 3):
        start = time.perf_counter()
        out = body(params)
        (out.vertices.square().sum() + out.keypoints.square().sum()
         + body.shape_prior(params).sum() * free_shape).backward()
        times.append(time.perf_counter() - start)
    return sorted(times[3:])[repeats // 2]


def run(out: Path, seed: int, frames: int, kinds: list[str], configs: list[str],
        batches: Sequence[int], sdf_dim: int = 256, rounds: int = 1, log=print) -> dict:
    """Fit every recording in every configuration and mode, ``rounds`` times, the modes in
    turn recording by recording (a batch is then timed seconds after the single frames it
    is compared with, not minutes); returns the figures per (configuration, mode), each
    recording's seconds the median of its rounds, and the body's unit costs."""
    torch.set_num_threads(1)
    body = AnnyBody.load()
    data = out / "data"
    recordings = make_benchmark(data, seed=seed, frames=frames, kinds=kinds, body=body)
    units: dict[str, list[float]] = {"frozen_shape": [], "free_shape": []}

    def measure_unit() -> float:
        """Both units measured now (recorded); returns the ratio's (shape free)."""
        units["frozen_shape"].append(body_seconds(body, False))
        units["free_shape"].append(body_seconds(body, True))
        return units["free_shape"][-1]

    scenes = {rec: truth_scene(data, rec, sdf_dim) for rec in recordings}
    kind_of = {rec: truth_meta(data, rec)["kind"] for rec in recordings}
    for rec in recordings:  # the fitter's SDFs, cached on disk before anything is timed
        load_scene(Recording(data, rec), sdf_dim)
    unit_before = measure_unit()  # right before the first fit
    modes = {"single": (1, False), "sequence": (1, True),
             **{f"batch {size}": (size, False) for size in batches}}
    rows = {}
    for name in configs:
        timed: dict[str, list[list[dict]]] = {mode: [] for mode in modes}  # [recording][round]
        fit_configs = {mode: dataclasses.replace(load_config(name), batch_size=size,
                                                 sdf_dim=sdf_dim)
                       for mode, (size, _) in modes.items()}
        for rec in recordings:
            for mode in modes:
                timed[mode].append([])
            for _ in range(rounds):
                for mode, (_, sequence) in modes.items():
                    start = time.perf_counter()
                    summary = fit_recording(data, rec, _fitted(out, name, mode),
                                            fit_configs[mode], body, sequence=sequence).summary
                    wall = time.perf_counter() - start
                    unit_after = measure_unit()
                    n = summary["frames_fitted"]
                    fit = summary["seconds_per_frame"] * n
                    timed[mode][-1].append({
                        "frames": n, "wall": wall, "fit": fit,
                        "evaluations": summary["body_evaluations_per_frame"] * n,
                        "units": fit / ((unit_before + unit_after) / 2),
                        "frames_seen": summary["frames"]})
                    unit_before = unit_after
        for mode, per_recording in timed.items():
            counted = sum(runs[0]["frames"] for runs in per_recording)

            def median(key: str) -> float:
                return sum(statistics.median(r[key] for r in runs)
                           for runs in per_recording) / counted

            errors = {rec: evaluate_recording(data, rec, _fitted(out, name, mode), body,
                                              scenes[rec]) for rec in recordings}
            per_kind: dict[str, list[dict]] = {}
            for rec, rec_errors in errors.items():
                per_kind.setdefault(kind_of[rec], []).extend(rec_errors)
            rows[(name, mode)] = {
                "wall_seconds_per_frame": median("wall"),
                "fit_seconds_per_frame": median("fit"),
                "body_evaluations_per_frame": median("evaluations"),
                "ratio": median("units"),
                "warm_started_seconds_per_frame": warm_started_seconds(
                    [f for runs in per_recording for r in runs for f in r["frames_seen"]]),
                "pje_mm": aggregate(sum(errors.values(), []))["pje"],
                "pje_mm_per_kind": {k: aggregate(e)["pje"] for k, e in per_kind.items()}}
            if mode.startswith("batch"):  # each round's single frames against its batches
                rows[(name, mode)]["speed_up_per_round"] = [
                    sum(runs[r]["fit"] for runs in timed["single"])
                    / sum(runs[r]["fit"] for runs in per_recording) for r in range(rounds)]
            log(f"{name:<10} {mode:<9} " + " ".join(
                f"{k} {v:.3g}" for k, v in rows[(name, mode)].items()
                if isinstance(v, float)))
    unit = {kind: statistics.median(times) for kind, times in units.items()}
    log(f"body forward+backward: {unit['frozen_shape'] * 1000:.1f} ms with the shape frozen, "
        f"{unit['free_shape'] * 1000:.1f} ms free (medians of {len(units['free_shape'])}; "
        f"free {min(units['free_shape']) * 1000:.1f}-{max(units['free_shape']) * 1000:.1f})")
    return {"unit_seconds": unit, "unit_samples": units, "rows": rows,
            "settings": {"seed": seed, "frames": frames, "kinds": kinds, "batch": list(batches),
                         "sdf_dim": sdf_dim, "rounds": rounds,
                         "threads": torch.get_num_threads()}}


def batch_costs(seconds: dict[int, float]) -> tuple[float, float]:
    """The seconds a frame of batches of N frames takes (``seconds``: N -> s a frame; 1:
    single frames) split by least squares into what every frame costs and what a batch
    costs whatever its size, s(N) = per_frame + per_batch / N: each evaluation's work on
    a frame's rows against the Python, kernel launches and small operations it costs once
    for all rows. Single frames' throughput times (per_frame + per_batch) / per_frame is
    then what no batch size can beat."""
    sizes = np.array(sorted(seconds), dtype=float)
    design = np.stack([np.ones_like(sizes), 1.0 / sizes], 1)
    (per_frame, per_batch), *_ = np.linalg.lstsq(
        design, np.array([seconds[int(n)] for n in sizes]), rcond=None)
    return float(per_frame), float(per_batch)


def _by_batch_size(rows: dict) -> str:
    """Per configuration fitted in two or more batch sizes: seconds a frame and
    throughput against single frames by batch size, and :func:`batch_costs`."""
    text = ""
    for name in dict.fromkeys(name for name, _ in rows):
        sizes = {int(mode.split()[1]): r["fit_seconds_per_frame"]
                 for (n, mode), r in rows.items() if n == name and mode.startswith("batch")}
        if len(sizes) < 2 or (name, "single") not in rows:
            continue
        single = rows[(name, "single")]["fit_seconds_per_frame"]
        sizes[1] = single
        per_frame, per_batch = batch_costs(sizes)
        text += (f"\n{name}, by batch size (s a frame, fit; throughput against single "
                 "frames; s(N) = per frame + per batch / N fitted to these):\n\n"
                 "| N | s/frame | x single | model |\n|---|---|---|---|\n")
        for size in sorted(sizes):
            text += (f"| {size} | {sizes[size]:.3f} | {single / sizes[size]:.2f} | "
                     f"{per_frame + per_batch / size:.3f} |\n")
        text += (f"\n{per_frame:.3f} s a frame and {per_batch:.3f} s a batch: no batch size "
                 f"beats {(per_frame + per_batch) / per_frame:.2f}x single frames' "
                 "throughput.\n")
    return text


def _fitted(out: Path, config: str, mode: str) -> Path:
    """Where a configuration's fits in a mode are written (each round over the last)."""
    return out / "fits" / config / mode.replace(" ", "")


def warm_started_seconds(frames: list[dict]) -> float | None:
    """Mean seconds of the frames (summary.json entries) fitted from a neighbour: neither
    the anchor nor refitted in the chain (a kept fit from scratch that carries its warm
    fit's cost, ``warm_fit``, counts: the path of least motion fits every such frame
    both ways); None if none."""
    warm = [f["seconds"] for f in frames if "warm_fit" in f.get("profile", {})
            or not {"initialise", "discarded_fit"} & set(f.get("profile", {}))]
    return sum(warm) / len(warm) if warm else None


def markdown(result: dict) -> str:
    unit = result["unit_seconds"]
    s = result["settings"]
    text = (f"Seed {s['seed']}, {s['frames']} frames x {len(s['kinds'])} kinds, "
            f"{s['threads']} thread. One body forward+backward: "
            f"{unit['frozen_shape'] * 1000:.1f} ms (shape frozen), "
            f"{unit['free_shape'] * 1000:.1f} ms (shape free; the ratio's unit), medians of "
            f"{len(result['unit_samples']['free_shape'])} measured between the fits, each "
            f"fit divided by the mean of the two around it; each recording fitted "
            f"{s['rounds']} time(s) in every mode, the modes in turn, its seconds the "
            f"median.\n\n"
            "| config | mode | s/frame (fit) | s/frame (wall) | body evaluations/frame "
            "| s/frame / body eval | s/frame warm-started | PJE mm |\n"
            "|---|---|---|---|---|---|---|---|\n")
    for (name, mode), r in result["rows"].items():
        text += (f"| {name} | {mode} | {r['fit_seconds_per_frame']:.2f} | "
                 f"{r['wall_seconds_per_frame']:.2f} | {r['body_evaluations_per_frame']:.0f} | "
                 f"{r['ratio']:.0f} | {_seconds(r['warm_started_seconds_per_frame'])} | "
                 f"{r['pje_mm']:.1f} |\n")
    text += _per_kind(result["rows"])
    for (name, mode), r in result["rows"].items():
        if "speed_up_per_round" in r:
            rounds = r["speed_up_per_round"]
            text += (f"\n{name}, {mode}: {statistics.median(rounds):.2f}x single frames' "
                     f"throughput (median of {len(rounds)} rounds: "
                     f"{', '.join(f'{x:.2f}' for x in rounds)}).\n")
    return text + _by_batch_size(result["rows"])


def _per_kind(rows: dict) -> str:
    """PJE per kind in every configuration and mode, and per configuration, each other
    mode's largest difference on a kind from its single frames (issue 14: none over
    3 mm)."""
    kinds = sorted({k for r in rows.values() for k in r["pje_mm_per_kind"]})
    text = ("\n| kind | " + " | ".join(f"{name}, {mode}" for name, mode in rows) + " |\n"
            + "|---" * (len(rows) + 1) + "|\n")
    for kind in kinds:
        text += (f"| {kind} | " + " | ".join(f"{r['pje_mm_per_kind'][kind]:.1f}"
                                            for r in rows.values()) + " |\n")
    text += "\n(PJE mm.)"
    for (name, mode), r in rows.items():
        single = rows.get((name, "single"))
        if mode == "single" or single is None:
            continue
        gap, kind = max((r["pje_mm_per_kind"][k] - single["pje_mm_per_kind"][k], k)
                        for k in kinds)
        text += f" {name}, {mode}: at most {gap:+.1f} mm on a kind against single frames ({kind})."
    return text + "\n"


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("speed_output"))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--kinds", nargs="+", default=["sit", "walk"], choices=KINDS)
    parser.add_argument("--configs", nargs="+", default=["rgb", "prox"])
    parser.add_argument("--batch", type=int, nargs="+", default=[8],
                        help="batch sizes, each a mode of its own")
    parser.add_argument("--sdf-dim", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=1,
                        help="fit each recording this many times in every mode, the modes "
                             "in turn; each recording's seconds are its rounds' median")
    args = parser.parse_args(argv)
    result = run(args.out, args.seed, args.frames, args.kinds, args.configs, args.batch,
                 args.sdf_dim, args.rounds)
    text = markdown(result)
    args.out.mkdir(parents=True, exist_ok=True)
    serialisable = {**result, "rows": [{"config": c, "mode": m, **r}
                                       for (c, m), r in result["rows"].items()]}
    atomic_write_text(args.out / "speed.json", json.dumps(serialisable, indent=1))
    atomic_write_text(args.out / "speed.md", text)
    print(text)


if __name__ == "__main__":
    main()
