"""`prox fit` on the synthetic sitting scene: outputs, bad frames, and prox vs rgb (the fits
are the session fixture ``cli_fits``)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import trimesh

from .conftest import REC, cli_fit, coarse_config


def test_outputs_in_prox_layout(cli_fits, body):
    out, run = cli_fits["prox"]
    summary = json.loads((out / REC / "summary.json").read_text())
    assert summary["frames_fitted"] == 2 and summary["frames_failed"] == 0
    frame = summary["frames"][0]["frame"]
    result = json.loads((out / REC / "results" / frame / "000.json").read_text())
    assert {"global_orient", "transl", "body_pose", "phenotype", "camera", "losses",
            "timings"} <= set(result)
    assert {"data", "penetration", "contact"} <= set(result["losses"])
    mesh = trimesh.load(out / REC / "meshes" / frame / "000.ply", process=False)
    assert len(mesh.vertices) == 13718
    assert np.array_equal(np.asarray(mesh.faces), body.faces.numpy())  # anny's vertex order
    assert "s/frame" in run.stdout and REC in run.stdout
    # written atomically, yet as readable as a plain open() makes files (not mkstemp's 0600)
    from prox_engine.output import UMASK
    for path in (out / REC / "summary.json", out / REC / "report" / "index.html",
                 out / REC / "report" / "sequence.mp4"):
        assert path.stat().st_mode & 0o777 == 0o666 & ~UMASK, path


def test_rgb_fit_follows_the_keypoints(cli_fits):
    out, _ = cli_fits["rgb"]
    summary = json.loads((out / REC / "summary.json").read_text())
    assert summary["reprojection_error_px"] < 10


def test_prox_penetrates_less_than_rgb(cli_fits):
    share = {}
    for name, (out, _) in cli_fits.items():
        summary = json.loads((out / REC / "summary.json").read_text())
        share[name] = summary["penetration"]["mean_penetrating_share"]
    assert share["prox"] < share["rgb"], share


def test_bad_frame_is_reported_and_skipped(sitting_data, tmp_path):
    base = tmp_path / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth"))
    (base / "keypoints" / REC / "a_broken_keypoints.json").write_text('{"people": []}')
    run = cli_fit(base, tmp_path / "out", coarse_config(tmp_path, "rgb"), "--frames", "2",
                  "--no-report")
    assert run.returncode == 0, run.stderr
    assert "a_broken_keypoints.json" in run.stderr and "'people' is empty" in run.stderr
    summary = json.loads((tmp_path / "out" / REC / "summary.json").read_text())
    assert summary["frames_fitted"] == 1 and summary["frames_failed"] == 1


def test_batched_frames_fit_like_single_frames(sitting_data, tmp_path, cli_fits):
    """--batch 2 fits both frames as one batch: each keeps its own body, as close to its
    keypoints as when fitted alone, and the profile counts the batch's body evaluations
    per frame."""
    run = cli_fit(sitting_data, tmp_path / "out", coarse_config(tmp_path, "rgb"),
                  "--frames", "2", "--batch", "2", "--no-report")
    assert run.returncode == 0, run.stderr
    batched = json.loads((tmp_path / "out" / REC / "summary.json").read_text())
    single = json.loads((cli_fits["rgb"][0] / REC / "summary.json").read_text())
    assert batched["frames_fitted"] == 2
    for b, s in zip(batched["frames"], single["frames"]):
        assert b["frame"] == s["frame"]
        assert b["reprojection_error_px"] < s["reprojection_error_px"] + 3
    assert 0 < batched["body_evaluations_per_frame"] == sum(
        stage["body_evaluations"] for stage in batched["profile"].values())


def test_missing_scene_is_a_clear_error(sitting_data, tmp_path):
    base = tmp_path / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth", "scenes"))
    run = cli_fit(base, tmp_path / "out", coarse_config(tmp_path, "rgb"), "--frames", "1")
    assert run.returncode == 1
    assert "Synthetic.ply: scene mesh not found" in run.stderr
    assert "Traceback" not in run.stderr
    assert "results in" not in run.stdout and not (tmp_path / "out").exists()


def test_every_frame_failing_is_a_failed_run(sitting_data, tmp_path):
    base = tmp_path / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth"))
    for path in (base / "keypoints" / REC).iterdir():
        path.write_text('{"people": []}')
    run = cli_fit(base, tmp_path / "out", coarse_config(tmp_path, "rgb"), "--no-report")
    assert run.returncode == 1
    assert f"{REC}: no frame could be fitted" in run.stderr


def test_sequence_mode_warm_starts(sitting_data, tmp_path):
    run = cli_fit(sitting_data, tmp_path / "seq", coarse_config(tmp_path, "prox"),
                  "--sequence", "--frames", "2")
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "seq" / REC / "summary.json").read_text())
    assert summary["sequence"] is True and summary["frames_fitted"] == 2
    first, second = (json.loads((tmp_path / "seq" / REC / "results" / f["frame"] / "000.json")
                                .read_text()) for f in summary["frames"])
    assert "temporal" in second["losses"] and "temporal" not in first["losses"]
    assert first["phenotype"] == second["phenotype"]  # shape frozen after the first frame
    assert list(second["timings"]["stages"]) == ["final", "contact"]  # keypoints, then scene
