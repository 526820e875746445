"""Seconds per frame, accuracy and penetration on the synthetic sitting scene.

    .venv/bin/python -m benchmarks.sitting_speed [--frames 5] [--out /tmp/prox-bench]

Fits rgb and prox, single-frame and sequence mode, one thread, and prints a table.
"""
from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from prox_engine.body.anny_body import AnnyBody
from prox_engine.config import load_config
from prox_engine.pipeline import fit_recording
from prox_engine.synthetic import make_sitting_dataset

REC = "Synthetic_00000_01"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("/tmp/prox-bench"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    body = AnnyBody.load()
    data = make_sitting_dataset(args.out / "data", frames=args.frames, body=body)
    faces = len(trimesh.load(data / "scenes" / "Synthetic.ply").faces)
    print(f"scene: {faces} faces; {args.frames} frames; 1 thread")
    print(f"{'config':<14} {'s/frame':>8} {'V2V mm':>7} {'pen %':>6} {'max pen cm':>10} "
          f"{'reproj px':>9}  contact")
    for name in ("rgb", "prox"):
        for sequence in (False, True):
            out = args.out / f"{name}{'-seq' if sequence else ''}"
            start = time.perf_counter()
            result = fit_recording(data, REC, out, load_config(name), body, sequence=sequence)
            wall = time.perf_counter() - start
            s = result.summary
            v2v = []
            for frame in s["frames"]:
                gt = np.load(data / "ground_truth" / REC / f"{frame['frame']}.npz")["vertices"]
                fit = trimesh.load(out / REC / "meshes" / frame["frame"] / "000.ply",
                                   process=False).vertices
                v2v.append(np.linalg.norm(fit - gt, axis=1).mean() * 1000)
            label = f"{name}{' seq' if sequence else ''}"
            print(f"{label:<14} {s['seconds_per_frame']:8.2f} {np.mean(v2v):7.0f} "
                  f"{100 * s['penetration']['mean_penetrating_share']:6.2f} "
                  f"{100 * s['penetration']['max_depth_m']:10.1f} "
                  f"{s['reprojection_error_px']:9.1f}  {s['contact']['parts']} "
                  f"(wall {wall:.0f} s incl. scene set-up {s['scene_setup_seconds']:.1f} s)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory: {peak:.0f} MB")


if __name__ == "__main__":
    main()
