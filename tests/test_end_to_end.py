"""`prox fit` on the synthetic sitting scene: outputs, bad frames, and prox vs rgb."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from prox_engine.config import CONFIG_DIR

REC = "Synthetic_00000_01"


def _config(tmp_path: Path, name: str) -> Path:
    """The named configuration on a coarser SDF grid, to keep the test quick."""
    path = tmp_path / f"{name}.yaml"
    path.write_text((CONFIG_DIR / f"{name}.yaml").read_text() + "sdf_dim: 128\n")
    return path


def _fit(base: Path, out: Path, config: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "prox_engine.cli", "fit", str(base), "--out",
                           str(out), "--config", str(config), *extra],
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def fits(sitting_data, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fits")
    runs = {}
    for name in ("rgb", "prox"):
        run = _fit(sitting_data, tmp / name, _config(tmp, name), "--frames", "1")
        assert run.returncode == 0, run.stderr
        runs[name] = (tmp / name, run)
    return runs


def test_outputs_in_prox_layout(fits, body):
    out, run = fits["prox"]
    summary = json.loads((out / REC / "summary.json").read_text())
    assert summary["frames_fitted"] == 1 and summary["frames_failed"] == 0
    frame = summary["frames"][0]["frame"]
    result = json.loads((out / REC / "results" / frame / "000.json").read_text())
    assert {"global_orient", "transl", "body_pose", "phenotype", "camera", "losses",
            "timings"} <= set(result)
    assert {"data", "penetration", "contact"} <= set(result["losses"])
    mesh = trimesh.load(out / REC / "meshes" / frame / "000.ply", process=False)
    assert len(mesh.vertices) == 13718
    assert np.array_equal(np.asarray(mesh.faces), body.faces.numpy())  # anny's vertex order
    assert "s/frame" in run.stdout and REC in run.stdout


def test_rgb_fit_follows_the_keypoints(fits):
    out, _ = fits["rgb"]
    summary = json.loads((out / REC / "summary.json").read_text())
    assert summary["reprojection_error_px"] < 10


def test_prox_penetrates_less_than_rgb(fits):
    share = {}
    for name, (out, _) in fits.items():
        summary = json.loads((out / REC / "summary.json").read_text())
        share[name] = summary["penetration"]["mean_penetrating_share"]
    assert share["prox"] < share["rgb"], share


def test_bad_frame_is_reported_and_skipped(sitting_data, tmp_path):
    base = tmp_path / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth"))
    (base / "keypoints" / REC / "a_broken_keypoints.json").write_text('{"people": []}')
    run = _fit(base, tmp_path / "out", _config(tmp_path, "rgb"), "--frames", "2")
    assert run.returncode == 0, run.stderr
    assert "a_broken_keypoints.json" in run.stderr and "'people' is empty" in run.stderr
    summary = json.loads((tmp_path / "out" / REC / "summary.json").read_text())
    assert summary["frames_fitted"] == 1 and summary["frames_failed"] == 1


def test_missing_scene_is_a_clear_error(sitting_data, tmp_path):
    base = tmp_path / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth", "scenes"))
    run = _fit(base, tmp_path / "out", _config(tmp_path, "rgb"), "--frames", "1")
    assert run.returncode == 1
    assert "Synthetic.ply: scene mesh not found" in run.stderr
    assert "Traceback" not in run.stderr


def test_sequence_mode_warm_starts(sitting_data, tmp_path):
    run = _fit(sitting_data, tmp_path / "seq", _config(tmp_path, "prox"), "--sequence",
               "--frames", "2")
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "seq" / REC / "summary.json").read_text())
    assert summary["sequence"] is True and summary["frames_fitted"] == 2
    first, second = (json.loads((tmp_path / "seq" / REC / "results" / f["frame"] / "000.json")
                                .read_text()) for f in summary["frames"])
    assert "temporal" in second["losses"] and "temporal" not in first["losses"]
    assert first["phenotype"] == second["phenotype"]  # shape frozen after the first frame
    assert list(second["timings"]["stages"]) == ["contact"]
