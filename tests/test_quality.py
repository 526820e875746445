"""Quality flags: a fit hidden behind the scan, floating or sunk in it, and the outliers of a
recording (reprojection error, distance from the camera, speed) are flagged; the ground
truth is not."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from prox_engine import metrics, quality
from prox_engine.dataset import Recording, frame_rate, frame_times
from prox_engine.keypoints import load_keypoints
from prox_engine.pipeline import load_scene

from .conftest import REC


def _flags(vertices, joints, confidence, body, scene) -> list[str]:
    stats, _ = metrics.scene_stats(vertices, body, scene)
    return [f["kind"] for f in quality.frame_flags(stats, vertices, joints, confidence,
                                                   scene)]


def _first_truth(data):
    """The sitting scene, and its first frame's true vertices, joints and detections."""
    rec = Recording(data, REC)
    name = rec.frames()[0]
    truth = np.load(data / "ground_truth" / REC / f"{name}.npz")
    return (load_scene(rec, 128), torch.as_tensor(truth["vertices"], dtype=torch.float32),
            torch.as_tensor(truth["joints"], dtype=torch.float32),
            load_keypoints(rec.keypoint_path(name)).confidence)


def test_a_body_pushed_behind_the_chair_back_is_flagged(sitting_data, body):
    """The demo's failure: a sitter fitted 30 cm too deep, through the thin chair back. The
    joints the detector saw are then behind the scan, seen from the camera."""
    scene, vertices, joints, confidence = _first_truth(sitting_data)
    assert _flags(vertices, joints, confidence, body, scene) == []
    scale = 1 + 0.30 / float(joints[8].norm())  # 30 cm farther along the camera rays
    hidden, seen = quality.hidden_joints(joints * scale, confidence, scene)
    assert seen >= 15 and hidden >= seen / 2
    assert "hidden" in _flags(vertices * scale, joints * scale, confidence, body, scene)


def test_floating_and_sunk_bodies_are_flagged(sitting_data, body):
    scene, vertices, joints, _ = _first_truth(sitting_data)
    confidence = np.zeros(118)  # nothing seen: only the scene decides
    up = scene.up_in_camera()
    assert _flags(vertices + 0.3 * up, joints + 0.3 * up, confidence, body, scene) == [
        "floating"]
    assert "sunk" in _flags(vertices - 0.2 * up, joints - 0.2 * up, confidence, body, scene)


def _frame(name: str, error: float, root: list[float]) -> dict:
    return {"frame": name, "reprojection_error_px": error, "root_m": root, "flags": []}


def test_recording_outliers_are_flagged():
    frames = [_frame("a", 5, [0, 0, 3.0]), _frame("b", 6, [0.05, 0, 3.0]),
              _frame("c", 40, [0.1, 0, 3.0]), _frame("d", 5, [0.1, 0, 4.2]),
              _frame("e", 6, [0.15, 0, 3.0])]
    quality.recording_flags(frames, [0.0, 1 / 30, 2 / 30, 3 / 30, 4 / 30])
    kinds = {f["frame"]: [flag["kind"] for flag in f["flags"]] for f in frames}
    assert kinds == {"a": [], "b": [], "c": ["reprojection"], "d": ["distance", "jump"],
                     "e": ["jump"]}
    # the same motion over seconds is a walk, not a jump
    slow = [_frame(f["frame"], 5, f["root_m"]) for f in frames]
    quality.recording_flags(slow, [0.0, 1.0, 2.0, 3.0, 4.0])
    assert [flag["kind"] for f in slow for flag in f["flags"]] == ["distance"]


def test_frame_times_and_rate_come_from_prox_frame_names():
    names = ["s001_frame_00001__00.00.00.029", "s001_frame_00002__00.00.00.062",
             "s001_frame_00004__00.00.00.129", "s001_frame_01801__00.01.00.000"]
    assert frame_times(names)[:3] == pytest.approx([0.029, 0.062, 0.129])
    assert frame_times(names)[3] == pytest.approx(60.0)
    assert frame_rate(names) == pytest.approx(30.0, abs=0.1)
    assert frame_times(["a", "b"]) == pytest.approx([0, 1 / 30])  # no stamps: Kinect's rate


def test_summary_carries_the_flags(cli_fits):
    out, _ = cli_fits["prox"]
    summary = json.loads((out / REC / "summary.json").read_text())
    for frame in summary["frames"]:
        assert isinstance(frame["flags"], list) and len(frame["root_m"]) == 3
    assert summary["flagged_frames"] == [{"frame": f["frame"], "flags": f["flags"]}
                                         for f in summary["frames"] if f["flags"]]


def test_flags_show_on_the_sequence_and_frame_pages(cli_fits, tmp_path):
    import shutil

    from prox_engine.report import build_report

    out, _ = cli_fits["prox"]
    results = tmp_path / REC
    shutil.copytree(out / REC, results)
    summary = json.loads((results / "summary.json").read_text())
    frame = summary["frames"][1]
    frame["flags"] = [{"kind": "hidden", "detail": "9 of the 14 joints <b>x</b>"}]
    summary["flagged_frames"] = [{"frame": frame["frame"], "flags": frame["flags"]}]
    (results / "summary.json").write_text(json.dumps(summary))
    build_report(results, data=out.parent / "data")
    index = (results / "report" / "index.html").read_text()
    page = (results / "report" / "frames" / f"{frame['frame']}.html").read_text()
    for html in (index, page):
        assert "<b>hidden</b>" in html and "9 of the 14 joints &lt;b&gt;x&lt;/b&gt;" in html
    other = summary["frames"][0]["frame"]
    assert "Probably a wrong fit" not in (results / "report" / "frames" / f"{other}.html"
                                         ).read_text()


def test_keypoint_errors_name_the_limb_the_fit_lost():
    """Each detected body keypoint's distance from the fit's projection, through an
    off-centre camera with unequal focal lengths: an arm whose detections moved 48 px is
    48 px off and the other limbs on their keypoints, a leg the detector did not report
    is left out, and the mean reprojection error is over the detected keypoints only."""
    from prox_engine.camera import Camera
    from prox_engine.keypoints import N_KEYPOINTS, Keypoints
    from prox_engine.metrics import keypoint_errors, limb_errors, reprojection_error

    camera = Camera(fx=900.0, fy=1150.0, cx=700.0, cy=380.0)
    joints = torch.tensor(np.random.default_rng(3).uniform([-0.6, -0.9, 2.5], [0.6, 0.9, 3.5],
                                                           (N_KEYPOINTS, 3)), dtype=torch.float32)
    data = np.zeros((N_KEYPOINTS, 3))
    data[:, :2] = camera.project(joints).numpy()
    data[:25, 2] = 0.9
    data[[5, 6, 7], 0] += 48.0  # the left arm
    data[[9, 10, 11], 2] = 0.0  # the right leg, not detected
    keypoints = Keypoints(data, has_hands=False, has_face=False)
    mask = torch.ones(N_KEYPOINTS, dtype=torch.bool)
    errors = keypoint_errors(joints, keypoints, camera, mask)
    assert torch.isnan(errors[[9, 10, 11]]).all()
    assert torch.allclose(errors[[5, 6, 7]], torch.full((3,), 48.0), atol=1e-2)
    limbs = limb_errors(errors)
    assert set(limbs) == {"right arm", "left arm", "left leg"}
    assert limbs["left arm"] == pytest.approx(48.0, abs=1e-2)
    assert limbs["right arm"] < 1e-2 and limbs["left leg"] < 1e-2
    assert reprojection_error(joints, keypoints, camera, mask) == pytest.approx(
        48.0 * 3 / 22, abs=1e-2)
    data[:25, 2] = 0.0
    assert limb_errors(keypoint_errors(joints, keypoints, camera, mask)) == {}
