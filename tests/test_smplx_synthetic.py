"""Self-check of the synthetic SMPL-X model file that the SMPL-X loader's tests use."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from .smplx_synthetic import EXTRA_VERTICES, JOINT_NAMES, SMPLX_PARENTS, write_smplx_model

V, J = 10475, 55


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> dict[str, np.ndarray]:
    path = write_smplx_model(tmp_path_factory.mktemp("smplx"))
    assert path.name == "SMPLX_NEUTRAL.npz"
    with np.load(path) as data:
        return dict(data)


def test_keys_shapes_dtypes(model):
    expected = {
        "v_template": ((V, 3), np.float64), "shapedirs": ((V, 3, 20), np.float64),
        "posedirs": ((V, 3, 486), np.float64), "J_regressor": ((J, V), np.float64),
        "weights": ((V, J), np.float64), "kintree_table": ((2, J), np.uint32),
        "hands_componentsl": ((45, 45), np.float64), "hands_componentsr": ((45, 45), np.float64),
        "hands_meanl": ((45,), np.float64), "hands_meanr": ((45,), np.float64),
        "lmk_faces_idx": ((51,), np.int64), "lmk_bary_coords": ((51, 3), np.float64),
        "dynamic_lmk_faces_idx": ((79, 17), np.int64),
        "dynamic_lmk_bary_coords": ((79, 17, 3), np.float64),
    }
    assert set(model) == set(expected) | {"f"}
    for key, (shape, dtype) in expected.items():
        assert model[key].shape == shape and model[key].dtype == dtype, key
    assert model["f"].dtype == np.uint32 and model["f"].ndim == 2 and model["f"].shape[1] == 3


def test_skeleton_and_skinning(model):
    reg, w = model["J_regressor"], model["weights"]
    assert np.allclose(reg.sum(axis=1), 1.0) and reg.min() >= 0.0
    assert np.allclose(w.sum(axis=1), 1.0) and w.min() >= 0.0
    joints = reg @ model["v_template"]
    y = dict(zip(JOINT_NAMES, joints[:, 1]))
    assert y["head"] > y["neck"] > y["pelvis"] > y["left_knee"] > y["left_ankle"] > -1.3
    assert joints[JOINT_NAMES.index("left_wrist"), 0] > 0.5
    assert joints[JOINT_NAMES.index("right_wrist"), 0] < -0.5
    height = np.ptp(model["v_template"][:, 1])
    assert 1.5 < height < 1.9
    kintree = model["kintree_table"].astype(np.int64)
    assert kintree[0, 0] == 2**32 - 1
    assert kintree[0, 1:].tolist() == SMPLX_PARENTS[1:] and SMPLX_PARENTS[0] == -1
    assert kintree[1].tolist() == list(range(J))
    assert len(JOINT_NAMES) == len(SMPLX_PARENTS) == J
    # every joint has its own part of the surface
    assert np.all(np.bincount(w.argmax(axis=1), minlength=J) > 0)


def test_special_vertices(model):
    v, w = model["v_template"], model["weights"]
    at = {name: v[i] for name, i in EXTRA_VERTICES.items()}
    head = model["J_regressor"][JOINT_NAMES.index("head")] @ v
    assert at["nose"][2] > head[2] + 0.05 and abs(at["nose"][0]) < 0.01
    assert at["leye"][0] > 0 > at["reye"][0] and min(at["leye"][2], at["reye"][2]) > head[2]
    assert at["lear"][0] > at["leye"][0] and at["rear"][0] < at["reye"][0]
    for tag in "LR":
        assert at[tag + "BigToe"][2] > at[tag + "Heel"][2] + 0.15
        assert at[tag + "SmallToe"][2] > at[tag + "Heel"][2] + 0.15
        assert at[tag + "Heel"][1] < -1.1
    assert abs(at["LBigToe"][0]) < abs(at["LSmallToe"][0])  # the big toe is on the inside
    wrist = model["J_regressor"][[JOINT_NAMES.index("left_wrist"),
                                  JOINT_NAMES.index("right_wrist")]] @ v
    for finger in ("thumb", "index", "middle", "ring", "pinky"):
        third = model["J_regressor"][JOINT_NAMES.index(f"left_{finger}3")] @ v
        tip = at[f"l{finger}"]
        assert tip[0] > third[0] > wrist[0, 0] + 0.05
        assert at[f"r{finger}"][0] < wrist[1, 0] - 0.05
        assert w[EXTRA_VERTICES[f"l{finger}"]].argmax() == JOINT_NAMES.index(f"left_{finger}3")
    assert w[EXTRA_VERTICES["nose"]].argmax() == JOINT_NAMES.index("head")


def test_mesh_and_landmarks(model):
    f = model["f"].astype(np.int64)
    assert f.max() < V and np.unique(f).size == V
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    # closed and consistently oriented: each directed edge once, its reverse also present
    assert len(set(map(tuple, edges))) == len(edges) == len(set(map(tuple, edges[:, ::-1])))
    assert set(map(tuple, edges)) == set(map(tuple, edges[:, ::-1]))
    lmk = model["lmk_faces_idx"]
    assert lmk.min() >= 0 and lmk.max() < len(f)
    dynamic = model["dynamic_lmk_faces_idx"]
    assert dynamic.min() >= 0 and dynamic.max() < len(f)
    assert np.allclose(model["lmk_bary_coords"].sum(axis=1), 1.0)
    assert np.allclose(model["dynamic_lmk_bary_coords"].sum(axis=2), 1.0)
    head = model["J_regressor"][JOINT_NAMES.index("head")] @ model["v_template"]
    centres = model["v_template"][f[lmk]].mean(axis=1)
    assert np.all(centres[:, 2] > head[2]) and np.all(centres[:, 1] > head[1] - 0.06)
    for side in "lr":
        comp = model[f"hands_components{side}"]
        assert np.allclose(comp @ comp.T, np.eye(45))
        assert 0.0 < np.abs(model[f"hands_mean{side}"]).max() < 1.0


def test_blend_shapes(tmp_path: Path):
    path = write_smplx_model(tmp_path, gender="male", num_betas=16, num_expression=4, seed=3)
    assert path == tmp_path / "SMPLX_MALE.npz"
    with np.load(path) as data:
        v, sd, w, reg = data["v_template"], data["shapedirs"], data["weights"], data["J_regressor"]
        posedirs = data["posedirs"]
    assert sd.shape == (V, 3, 20)
    pelvis = reg[0] @ v
    assert np.allclose(sd[:, :, 0], 0.03 * (v - pelvis))
    assert 0.002 < np.abs(sd[:, :, 1:16]).max() < 0.05
    on_head = np.isin(w.argmax(axis=1), [15, 22, 23, 24])
    assert np.all(sd[~on_head, :, 16:] == 0.0) and np.abs(sd[on_head, :, 16:]).max() > 1e-3
    assert 1e-4 < posedirs.std() < 1e-2
