"""Every malformed input gives a clear error naming the file."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from prox_engine.config import load_config
from prox_engine.dataset import (load_calibration, load_cam2world, load_scene_mesh,
                                 load_scene_scan)
from prox_engine.errors import InputError
from prox_engine.keypoints import load_keypoints


def _person(n=25, value=1.0, conf=0.9):
    return [v for _ in range(n) for v in (value, value, conf)]


def _write(path, content):
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


@pytest.mark.parametrize("content, message", [
    ({"people": []}, "'people' is empty"),
    ({"nobody": 1}, "no 'people' list"),
    ("{not json", "not valid JSON"),
    ({"people": [{"pose_keypoints_2d": [1.0] * 74}]}, "must hold 75 numbers"),
    ({"people": [{"pose_keypoints_2d": _person(value=float("nan"))}]}, "NaN"),
    ({"people": [{"pose_keypoints_2d": _person(),
                  "hand_left_keypoints_2d": [0.0] * 60}]}, "'hand_left_keypoints_2d' must hold"),
    ({"people": [{"pose_keypoints_2d": _person(conf=0.0)}]}, "zero confidence"),
    ({"people": [{"face_keypoints_2d": _person(70)}]}, "without 'pose_keypoints_2d'"),
])
def test_bad_keypoint_files(tmp_path, content, message):
    path = _write(tmp_path / "f_keypoints.json", content)
    with pytest.raises(InputError) as err:
        load_keypoints(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_missing_keypoint_file(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        load_keypoints(tmp_path / "absent_keypoints.json")


def test_main_person_is_the_most_confident(tmp_path):
    weak = {"pose_keypoints_2d": _person(value=5.0, conf=0.2)}
    strong = {"pose_keypoints_2d": _person(value=7.0, conf=0.8),
              "hand_right_keypoints_2d": _person(21, 3.0, 0.5),
              "face_keypoints_2d": _person(70, 2.0, 0.4)}
    kp = load_keypoints(_write(tmp_path / "a_keypoints.json", {"people": [weak, strong]}))
    assert kp.data[0, 0] == 7.0 and kp.has_hands and kp.has_face
    assert kp.data.shape == (118, 3)
    assert kp.data[46, 0] == 3.0 and kp.data[25, 2] == 0  # right hand set, left hand missing


def test_calibration_errors(tmp_path):
    with pytest.raises(InputError, match="needs 'f'"):
        load_calibration(_write(tmp_path / "Color.json", {"c": [1, 2]}))
    with pytest.raises(InputError, match="positive"):
        load_calibration(_write(tmp_path / "Color.json", {"f": [-1, 1], "c": [1, 2]}))
    with pytest.raises(InputError, match="'c' must have 2"):
        load_calibration(_write(tmp_path / "Color.json", {"f": [1, 1], "c": [1]}))
    cam = load_calibration(_write(tmp_path / "Color.json",
                                  {"f": [1060.5, 1060.4], "c": [951.3, 536.8], "k": [0.1, 0.0]}))
    assert cam.fx == 1060.5 and cam.cy == 536.8 and cam.k == [0.1, 0.0]


def test_cam2world_errors(tmp_path):
    singular = np.eye(4)
    singular[2, 2] = 0
    with pytest.raises(InputError, match="singular") as err:
        load_cam2world(_write(tmp_path / "S.json", singular.tolist()))
    assert "S.json" in str(err.value)
    scaled = np.eye(4) * 2
    scaled[3, 3] = 1
    with pytest.raises(InputError, match="proper rotation"):
        load_cam2world(_write(tmp_path / "S.json", scaled.tolist()))
    with pytest.raises(InputError, match="16 numbers"):
        load_cam2world(_write(tmp_path / "S.json", [[1, 0], [0, 1]]))
    with pytest.raises(InputError, match="NaN"):
        load_cam2world(_write(tmp_path / "S.json", [[float("nan")] * 4] * 4))


def test_unreadable_mesh(tmp_path):
    path = tmp_path / "Room.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n garbage")
    with pytest.raises(InputError) as err:
        load_scene_mesh(path)
    assert "Room.ply" in str(err.value)
    with pytest.raises(InputError, match="not found"):
        load_scene_mesh(tmp_path / "Missing.ply")


def test_a_ply_scan_reads_as_trimesh_reads_it(tmp_path):
    """PLY scans are read without building a trimesh mesh (no per-face colours, no
    hashing), to the same arrays and vertex colours; a PLY of quads still comes out as
    triangles."""
    import trimesh

    scan = trimesh.creation.icosphere(subdivisions=2)
    scan.visual.vertex_colors = np.tile([200, 180, 160, 255], (len(scan.vertices), 1))
    for encoding in ("binary", "ascii"):
        path = tmp_path / f"Room_{encoding}.ply"
        path.write_bytes(scan.export(file_type="ply", encoding=encoding))
        expected = trimesh.load(path, force="mesh", process=False)
        for content in (None, path.read_bytes()):
            vertices, faces = load_scene_mesh(path, content)
            assert vertices.dtype == np.float64 and faces.dtype == np.int64
            np.testing.assert_array_equal(vertices, expected.vertices)
            np.testing.assert_array_equal(faces, expected.faces)
            np.testing.assert_array_equal(load_scene_scan(path, content).colours,
                                          expected.visual.vertex_colors)
    quads = tmp_path / "Quads.ply"
    quads.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                     "property float y\nproperty float z\nelement face 1\n"
                     "property list uchar int vertex_indices\nend_header\n"
                     "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    scan = load_scene_scan(quads)
    assert scan.faces.shape == (2, 3) and len(scan.vertices) == 4 and scan.colours is None


def test_configs(tmp_path):
    for name in ("rgb", "prox", "smplifyd", "proxd"):
        config = load_config(name)
        assert config.stages and config.name == name
    assert load_config("prox").uses("contact") and not load_config("rgb").uses("penetration")
    assert load_config("proxd").uses("depth")
    with pytest.raises(InputError, match="unknown configuration"):
        load_config("nope")
    bad = _write(tmp_path / "bad.yaml", "stages:\n  - {body: 1, wings: 2}\n")
    with pytest.raises(InputError, match="unknown terms"):
        load_config(bad)
    typo = _write(tmp_path / "typo.yaml", "base: prox\nswap_check_parts: [legs, arm]\n")
    with pytest.raises(InputError, match=r"swap_check_parts: unknown parts \['arm'\]"):
        load_config(typo)


@pytest.mark.parametrize("setting, problem", [
    ("scale_size_weight: high", "scale_size_weight: expected a number, got 'high'"),
    ("floating_restart: 1", "floating_restart: expected true or false, got 1"),
    ("batch_size: 2.5", "batch_size: expected a whole number, got 2.5"),
    ("swap_check_parts: legs", "swap_check_parts: expected a list of texts, got 'legs'"),
    ("model_path: 3", "model_path: expected a text or nothing, got 3"),
])
def test_a_setting_of_the_wrong_type_is_an_error_naming_the_file(tmp_path, setting, problem):
    """Each setting is read as FitConfig types it: one of the wrong kind failed deep in a
    worker's fit. YAML 1.1 reads 1e-2 (no point) as text; it is the number."""
    bad = _write(tmp_path / "typed.yaml", f"base: prox\n{setting}\n")
    with pytest.raises(InputError, match=re.escape(f"typed.yaml: {problem}")):
        load_config(bad)
    exponent = _write(tmp_path / "exponent.yaml", "base: prox\nscale_size_weight: 1e-2\n")
    assert load_config(exponent).scale_size_weight == 0.01


def test_config_inherits_from_its_base(tmp_path):
    """A configuration names a base and overrides some of its settings; cycles are an
    error naming the file."""
    own = _write(tmp_path / "mine.yaml", "base: prox\nswap_sides: false\ncontact_rho: 0.1\n")
    config, prox = load_config(own), load_config("prox")
    assert not config.swap_sides and config.contact_rho == 0.1 and config.name == "mine"
    assert [s.weights for s in config.stages] == [s.weights for s in prox.stages]
    child = _write(tmp_path / "child.yaml", "base: mine.yaml\nmax_iter: 5\n")
    assert load_config(child).max_iter == 5 and not load_config(child).swap_sides
    loop = _write(tmp_path / "loop.yaml", "base: loop.yaml\n")
    with pytest.raises(InputError, match="cycle"):
        load_config(loop)
    assert not load_config("prox-no-swaps").swap_sides
    assert not load_config("prox-no-scale-search").scale_search
    assert load_config("prox-no-facing").facing_cost == 0 < load_config("prox").facing_cost


def test_fit_help_lists_every_built_in_configuration():
    import os
    import subprocess
    import sys

    from prox_engine.config import CONFIG_DIR

    run = subprocess.run([sys.executable, "-m", "prox_engine.cli", "fit", "--help"],
                         capture_output=True, text=True, check=True,
                         env={**os.environ, "COLUMNS": "400"})
    for path in CONFIG_DIR.glob("*.yaml"):
        assert path.stem in run.stdout, path.stem
