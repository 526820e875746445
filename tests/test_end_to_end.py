"""`prox fit` on the synthetic sitting scene: outputs, bad frames, and prox vs rgb (the fits
are the session fixture ``cli_fits``)."""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from prox_engine.keypoints import side_swap

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
    # the person's height: each frame's from its fitted shape, the recording's their median
    from prox_engine.body.anny_body import PHENOTYPES
    shape = body.init_params(1)
    shape["shape"] = torch.logit(torch.tensor([[result["phenotype"][k] for k in PHENOTYPES]]))
    assert summary["frames"][0]["stature_m"] == pytest.approx(
        float(body.stature(shape)[0]), abs=1e-3)
    statures = [f["stature_m"] for f in summary["frames"]]
    assert all(1.3 < s < 2.1 for s in statures), statures
    assert summary["stature_m"] == pytest.approx(float(np.median(statures)))
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


def _sequence_fit_with(sitting_data, tmp_path, index: int, edit, *extra: str,
                       config: str = "prox-chain-only", settings: str = ""
                       ) -> tuple[dict, Path]:
    """``prox fit --sequence`` (by default the chain's fits alone: no path of least motion
    through fits from scratch; ``settings`` added to the configuration) of the first two
    sitting frames after ``edit`` changed the flat ``pose_keypoints_2d`` list of frame
    ``index``; the summary and that frame's file."""
    base = tmp_path / "data"
    shutil.copytree(sitting_data, base, ignore=shutil.ignore_patterns("ground_truth"))
    path = sorted((base / "keypoints" / REC).iterdir())[index]
    content = json.loads(path.read_text())
    edit(content["people"][0]["pose_keypoints_2d"])
    path.write_text(json.dumps(content))
    run = cli_fit(base, tmp_path / "seq", coarse_config(tmp_path, config, settings), "--sequence",
                  "--frames", "2", *extra)
    assert run.returncode == 0, run.stderr
    return json.loads((tmp_path / "seq" / REC / "summary.json").read_text()), path


def test_sequence_mode_starts_from_the_best_seen_frame(sitting_data, tmp_path):
    """The first frame is cut off below the knees: sequence mode fits the second frame,
    the one the detector saw best, from scratch, then the first warm-started from it
    (the temporal term on, its scale searched again); the summary lists the frames in
    their order."""
    def hide_feet(points: list[float]) -> None:
        for k in (11, 14, 19, 20, 21, 22, 23, 24):  # ankles and feet
            points[3 * k:3 * k + 3] = [0.0, 0.0, 0.0]

    summary, first_json = _sequence_fit_with(sitting_data, tmp_path, 0, hide_feet)
    assert summary["sequence"] is True and summary["frames_fitted"] == 2
    names = [f["frame"] for f in summary["frames"]]
    assert names == sorted(names) and first_json.name.startswith(names[0])
    first, second = (json.loads((tmp_path / "seq" / REC / "results" / name / "000.json")
                                .read_text()) for name in names)
    assert "temporal" in first["losses"] and "temporal" not in second["losses"]
    # keypoints, the frame's scale, then scene, then whether the fit floats
    # (pipeline._unless_floating)
    assert list(first["timings"]["stages"]) == ["final", "scale_search", "contact",
                                                "floating_check"]


def test_sequence_mode_keeps_the_fits_on_the_path_of_least_motion(sitting_data, tmp_path):
    """`prox`'s sequence mode fits each frame from scratch too and keeps, frame by frame,
    the fit on the path along which the body moves least. The first frame, cut off below
    the knees, follows the anchor (the second): its fit from scratch lies nearer the
    anchor's than its warm-started fit and is kept, the warm fit's cost charged to it; the
    anchor, fitted from scratch in the chain, has no other fit."""
    def hide_feet(points: list[float]) -> None:
        for k in (11, 14, 19, 20, 21, 22, 23, 24):
            points[3 * k:3 * k + 3] = [0.0, 0.0, 0.0]

    summary, _ = _sequence_fit_with(sitting_data, tmp_path, 0, hide_feet, "--no-report",
                                    config="prox")
    first, anchor = summary["frames"]
    assert "anchor_search" in anchor["profile"] or "initialise" in anchor["profile"]
    assert not {"warm_fit", "fresh_fit"} & set(anchor["profile"])
    kept = [e for e in first["events"] if "kept its fit from scratch" in e]
    assert len(kept) == 1, first["events"]
    moved, warm = (float(x) for x in re.findall(r"([\d.]+) cm", kept[0]))
    assert moved < warm, kept[0]
    assert first["profile"]["warm_fit"]["body_evaluations"] > 0
    assert first["seconds"] >= sum(s["seconds"] for s in first["profile"].values()) - 1e-3


@pytest.fixture(scope="module")
def three_frames(tmp_path_factory, body) -> Path:
    """The synthetic sitting scene with three frames."""
    from prox_engine.synthetic import make_sitting_dataset

    return make_sitting_dataset(tmp_path_factory.mktemp("three"), frames=3, body=body,
                                face_size=0.12)


def test_sequence_mode_goes_on_from_the_fit_the_path_kept(three_frames, tmp_path):
    """With a window of one frame, the chain's second frame, whose keypoints are the
    first's, keeps its fit from scratch (the first frame's fit to the bit: no motion) on
    the path of least motion, and the third frame is warm-started from that fit
    (``sequence_chain_from_path``), not from the chain's own."""
    base = tmp_path / "data"
    shutil.copytree(three_frames, base, ignore=shutil.ignore_patterns("ground_truth"))
    first_file, second_file, _ = sorted((base / "keypoints" / REC).iterdir())
    second_file.write_bytes(first_file.read_bytes())
    config = tmp_path / "windowed.yaml"
    config.write_text("base: prox\nsdf_dim: 128\nsequence_path_window: 1\n")
    run = cli_fit(base, tmp_path / "seq", config, "--sequence", "--frames", "3", "--no-report")
    assert run.returncode == 0, run.stderr
    first, second, third = json.loads((tmp_path / "seq" / REC / "summary.json").read_text()
                                      )["frames"]
    assert "initialise" in first["profile"]  # the anchor, the only frame of its window
    assert any("kept its fit from scratch" in e for e in second["events"]), second["events"]
    went_on = [e for e in third["events"] if "warm-started from" in e]
    assert len(went_on) == 1 and second["frame"] in went_on[0], third["events"]
    assert "temporal" in json.loads((tmp_path / "seq" / REC / "results" / third["frame"]
                                     / "000.json").read_text())["losses"]


def test_sequence_mode_anchors_on_a_frame_labelled_as_detected(sitting_data, tmp_path):
    """The detector exchanged the first frame's legs: sequence mode anchors on the second,
    as well seen and whose start keeps the detector's left and right, so that no relabelling
    is passed on to the whole sequence; the first, fitted after it, is relabelled, and the
    start searches spent choosing count in the anchor's time."""
    def swap_legs(points: list[float]) -> None:
        pose = np.asarray(points).reshape(25, 3)
        points[:] = pose[side_swap(("legs",))[:25]].ravel().tolist()

    summary, _ = _sequence_fit_with(sitting_data, tmp_path, 0, swap_legs, "--no-report")
    first, second = summary["frames"]
    assert "anchor_search" in second["profile"] and "anchor_search" not in first["profile"]
    assert second["sides_swapped"] == [] and first["sides_swapped"] == ["legs"]
    assert second["profile"]["anchor_search"]["body_evaluations"] > 0
    assert second["seconds"] >= sum(s["seconds"] for s in second["profile"].values()) - 1e-3


def _jump(points: list[float]) -> None:
    """Every keypoint seen moved 400 px to the left (a cut in the video)."""
    for k in range(0, len(points), 3):
        if points[k + 2] > 0:
            points[k] -= 400.0


def test_sequence_mode_refits_a_frame_whose_neighbour_lost_it(sitting_data, tmp_path):
    """The second frame's keypoints jump 400 px (a cut in the video): warm-started from
    the first frame's fit the body cannot follow, so the frame is fitted again from
    scratch, that fit kept and the event recorded; the frame's time counts both fits."""
    summary, _ = _sequence_fit_with(sitting_data, tmp_path, 1, _jump, "--no-report")
    first, second = summary["frames"]
    assert not any("refitted" in e for e in first["events"])
    assert any("refitted from scratch" in e for e in second["events"]), second["events"]
    assert second["reprojection_error_px"] < 3 * max(first["reprojection_error_px"], 5.0)
    profile = second["profile"]
    assert profile["discarded_fit"]["body_evaluations"] > 0
    assert second["seconds"] >= sum(stage["seconds"] for stage in profile.values()) - 1e-3


@pytest.mark.parametrize("window", [8, 1])
def test_sequence_mode_fits_no_frame_from_scratch_twice(sitting_data, tmp_path, window):
    """A frame whose warm fit lost the keypoints (a 400 px cut) falls back on the fit from
    scratch that the path of least motion has of it (made ahead for the anchor's choice
    with a window of 8, made then and held for the path with a window of 1): the path has
    no second fit from scratch to weigh against it, and the frame's time counts its two
    fits, the warm one discarded."""
    summary, _ = _sequence_fit_with(sitting_data, tmp_path, 1, _jump, "--no-report",
                                    config="prox", settings=f"sequence_path_window: {window}\n")
    refitted = [f for f in summary["frames"]
                if any("refitted from scratch" in e for e in f["events"])]
    assert len(refitted) == 1, [f["events"] for f in summary["frames"]]
    profile = refitted[0]["profile"]
    assert profile["discarded_fit"]["body_evaluations"] > 0
    assert not {"fresh_fit", "warm_fit"} & set(profile), profile
    assert not any("path of least motion" in e for e in refitted[0]["events"])
    assert refitted[0]["seconds"] >= sum(s["seconds"] for s in profile.values()) - 1e-3


def test_sequence_mode_refits_a_lost_fit_and_optionally_a_chain_overriding_the_detector():
    """A warm fit that lost the keypoints (over twice the anchor's error and 40 px), or one
    limb's (over four times the anchor's error, 20 px and 2.5 times any other limb's:
    blur spreads over every limb), is refitted from scratch whatever its labels; one that a
    blurred frame puts 12-30 px off is kept. With `sequence_side_refit`
    (`prox-side-refit`), so is a chain whose labelling overrides the detector on the same
    part for the second frame running; one override, or overrides of different parts
    (two independent detector swaps), keep the warm fit.
    Each reason has its switch."""
    from prox_engine.config import load_config
    from prox_engine.pipeline import refit_reason

    prox, sides = load_config("prox"), load_config("prox-side-refit")
    assert "px off" in refit_reason(prox, 50.0, 5.0, [], [])
    assert "px off" in refit_reason(prox, 90.0, 30.0, ["legs"], ["legs"])
    assert refit_reason(prox, 30.0, 5.0, [], []) == ""
    assert refit_reason(prox, 70.0, 40.0, [], []) == ""
    assert refit_reason(prox, 6.0, 5.0, ["legs"], ["legs"]) == ""
    arm = {"right arm": 60.0, "left arm": 8.0, "left leg": 6.0}
    assert "right arm 60 px off" in refit_reason(prox, 9.0, 5.0, [], [], arm)
    assert refit_reason(prox, 9.0, 16.0, [], [], arm) == ""  # under 4 times the anchor's
    assert refit_reason(prox, 9.0, 3.0, [], [], {"left leg": 18.0, "left arm": 3.0}) == ""
    assert refit_reason(prox, 9.0, 5.0, [], [], {**arm, "left arm": 30.0}) == ""  # blur
    assert refit_reason(prox, 9.0, 5.0, [], [], {"right arm": 60.0}) == ""  # nothing to compare
    assert refit_reason(load_config("prox-no-limb-refit"), 9.0, 5.0, [], [], arm) == ""
    assert "legs for the second frame" in refit_reason(sides, 6.0, 5.0, ["legs"], ["legs"])
    assert "arms for the second" in refit_reason(sides, 6.0, 5.0, ["arms"], ["legs", "arms"])
    assert refit_reason(sides, 6.0, 5.0, ["arms"], ["legs"]) == ""
    assert refit_reason(sides, 6.0, 5.0, [], ["legs"]) == ""
    assert refit_reason(sides, 6.0, 5.0, ["legs"], []) == ""
    assert refit_reason(load_config("prox-no-refit"), 90.0, 5.0, ["legs"], ["legs"]) == ""
