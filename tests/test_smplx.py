"""The SMPL-X backend on a synthetic model file in the SMPL-X format (tests/smplx_synthetic.py):
loading and its errors, linear blend skinning against a plain reference, the OpenPose
mapping, PCA hands, PROX's body segments, and a fit through `prox fit` with a 000.pkl."""
from __future__ import annotations

import json
import pickle
import subprocess
import sys

import numpy as np
import pytest
import torch

from prox_engine.errors import InputError
from prox_engine.geometry import axis_angle_to_matrix
from prox_engine.camera import Camera
from prox_engine.keypoints import BODY, FACE, LEFT_HAND, N_KEYPOINTS, RIGHT_HAND

from prox_engine.body import smplx_body
from prox_engine.body.smplx_body import SMPLXBody
from prox_engine.body.vposer import SNAPSHOT_SHAPES, VPoser

from .smplx_synthetic import EXTRA_VERTICES, SMPLX_PARENTS, write_smplx_model


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("smplx")
    for gender in ("NEUTRAL", "FEMALE"):
        write_smplx_model(folder, gender, seed=len(gender))
    return folder


@pytest.fixture(scope="module")
def smplx(model_dir):
    return SMPLXBody.load(model_dir, "neutral")


def _random_params(body, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    params = body.init_params(2)
    for name, value in params.items():
        params[name] = torch.randn(value.shape, generator=g) * (0.3 if name != "transl" else 1)
    return params


def _reference_lbs(data: dict, params: dict, index: int, fingers: np.ndarray) -> np.ndarray:
    """Textbook linear blend skinning in numpy, joint by joint, for one batch element."""
    betas = torch.cat([params["betas"][index], params["expression"][index]]).numpy()
    shaped = data["v_template"] + data["shapedirs"][..., :20] @ betas
    joints = data["J_regressor"] @ shaped
    pose = np.concatenate([params["global_orient"][index][None].numpy(),
                           params["body_pose"][index].numpy(),
                           params["jaw_pose"][index][None].numpy(), np.zeros((2, 3)), fingers])
    rot = axis_angle_to_matrix(torch.tensor(pose, dtype=torch.float32)).double().numpy()
    feature = (rot[1:] - np.eye(3)).reshape(-1)
    posed = shaped + (data["posedirs"] @ feature)
    world = []
    for j, parent in enumerate(SMPLX_PARENTS):
        local = np.eye(4)
        local[:3, :3] = rot[j]
        local[:3, 3] = joints[j] - (joints[parent] if parent >= 0 else 0)
        world.append(local if parent < 0 else world[parent] @ local)
    out = np.zeros_like(posed)
    for j, transform in enumerate(world):
        moved = (posed - joints[j]) @ transform[:3, :3].T + transform[:3, 3]
        out += data["weights"][:, j:j + 1] * moved
    return out + params["transl"][index].numpy()


def test_skinning_matches_a_plain_reference(smplx, model_dir):
    data = dict(np.load(model_dir / "SMPLX_NEUTRAL.npz"))
    params = _random_params(smplx)
    with torch.no_grad():
        out = smplx(params)
    for b in range(2):
        expected = _reference_lbs(data, params, b, smplx.finger_pose(params)[b].numpy())
        assert np.abs(out.vertices[b].numpy() - expected).max() < 1e-4


@pytest.mark.parametrize("which", ["smplx", "anny"])
def test_root_turns_the_body_about_its_pivot(smplx, body, which):
    """Body keypoints are R (k - pivot) + pivot + transl of the unturned, untranslated
    ones, which the start search relies on, for each posture it starts from."""
    from prox_engine.geometry import axis_angle_to_matrix

    model = smplx if which == "smplx" else body
    for posture in model.postures:
        params = model.init_params(1, posture)
        with torch.no_grad():
            rest = model(params).keypoints[0, :25]
            pivot = model.root_pivot(params)[0]
            params["global_orient"][0] = torch.tensor([0.4, -1.1, 0.7])
            params["transl"][0] = torch.tensor([0.3, -0.2, 2.5])
            turned = model(params).keypoints[0, :25]
        rotation = axis_angle_to_matrix(params["global_orient"])[0]
        expected = (rest - pivot) @ rotation.T + pivot + params["transl"][0]
        assert torch.allclose(turned, expected, atol=1e-4), posture


def test_start_search_places_smplx_on_its_keypoints(smplx):
    """The start search puts an SMPL-X body (whose root turns about its pelvis joint, not
    the origin) where its keypoints are."""
    from prox_engine.camera import Camera
    from prox_engine.config import load_config
    from prox_engine.fitting import Fitter, Frame
    from prox_engine.keypoints import N_KEYPOINTS, Keypoints

    camera = Camera(1000.0, 1000.0, 960.0, 540.0)
    params = smplx.init_params(1)
    params["global_orient"][0] = torch.tensor([3.0, 0.3, 0.0])  # upright before a camera
    params["transl"][0] = torch.tensor([0.2, 0.1, 3.0])
    with torch.no_grad():
        truth = smplx(params).keypoints[0, :25]
    data = np.zeros((N_KEYPOINTS, 3))
    data[:25, :2], data[:25, 2] = camera.project(truth).numpy(), 0.9
    fitter = Fitter(smplx, camera, load_config("rgb"))
    start, _ = fitter.initialise([Frame("f", Keypoints(data, False, False))])
    with torch.no_grad():
        placed = smplx(start).keypoints[0, :25]
    torso = [2, 5, 9, 12]
    assert float((placed[torso] - truth[torso]).norm(dim=-1).mean()) < 0.1


def test_rest_pose_and_keypoint_mapping(model_dir):
    data = dict(np.load(model_dir / "SMPLX_NEUTRAL.npz"))
    smplx = SMPLXBody.load(model_dir, "neutral", hand_pca=0)
    params = smplx.init_params(1)
    params["hand_pose"] = -smplx.hand_mean.view(1, 30, 3)  # flat hands: the template's
    with torch.no_grad():
        out = smplx(params)
    vertices, keypoints = out.vertices[0].numpy(), out.keypoints[0].numpy()
    assert np.allclose(vertices, data["v_template"], atol=1e-5)
    joints = data["J_regressor"] @ data["v_template"]
    body = keypoints[BODY]
    assert np.allclose(body[1], joints[12], atol=1e-5)  # neck
    assert np.allclose(body[8], joints[0], atol=1e-5)  # mid-hip: the pelvis
    assert np.allclose(body[2], joints[17], atol=1e-5) and np.allclose(body[5], joints[16],
                                                                        atol=1e-5)
    assert np.allclose(body[0], vertices[EXTRA_VERTICES["nose"]])
    assert np.allclose(body[19], vertices[EXTRA_VERTICES["LBigToe"]])
    assert np.allclose(body[24], vertices[EXTRA_VERTICES["RHeel"]])
    left, right = keypoints[LEFT_HAND], keypoints[RIGHT_HAND]
    assert np.allclose(left[0], joints[20], atol=1e-5) and np.allclose(right[0], joints[21],
                                                                        atol=1e-5)
    assert np.allclose(left[4], vertices[EXTRA_VERTICES["lthumb"]])
    assert np.allclose(right[20], vertices[EXTRA_VERTICES["rpinky"]])
    faces = data["f"][data["lmk_faces_idx"]]
    landmarks = np.einsum("lkd,lk->ld", vertices[faces], data["lmk_bary_coords"])
    assert np.allclose(keypoints[FACE], landmarks, atol=1e-5)
    assert smplx.keypoint_mask.all()
    # The regressor the benchmark uses gives the same BODY_25 points at rest.
    assert np.allclose(smplx.keypoint_weights.numpy() @ vertices, body, atol=1e-5)


def test_hands_from_pca_or_every_joint(model_dir, smplx):
    data = dict(np.load(model_dir / "SMPLX_NEUTRAL.npz"))
    params = smplx.init_params(1)
    assert params["hand_pose"].shape == (1, 24)
    rest = smplx.finger_pose(params)[0].reshape(2, 45).numpy()
    assert np.allclose(rest[0], data["hands_meanl"]) and np.allclose(rest[1], data["hands_meanr"])
    params["hand_pose"][0, 0] = 1.0  # first left component
    moved = smplx.finger_pose(params)[0].reshape(2, 45).numpy()
    assert np.allclose(moved[0] - rest[0], data["hands_componentsl"][0], atol=1e-6)
    full = SMPLXBody.load(model_dir, "neutral", hand_pca=0)
    params = full.init_params(1)
    assert params["hand_pose"].shape == (1, 30, 3)
    assert np.allclose(full.finger_pose(params)[0].reshape(2, 45).numpy(), rest)  # the mean


@pytest.mark.parametrize("hand_pca", [12, 0])
def test_pkl_read_as_smplifyx_reads_it_gives_our_vertices(model_dir, hand_pca):
    """000.pkl's hands, read as SMPLify-X and PROX read them (``flat_hand_mean=False``: the
    mean hand added to the PCA decoding, or to the 45 rotations without PCA), and its other
    arrays, skinned by a plain reference, give back our vertices; the JSON's hand poses and
    convention say the same."""
    data = dict(np.load(model_dir / "SMPLX_NEUTRAL.npz"))
    smplx = SMPLXBody.load(model_dir, "neutral", hand_pca=hand_pca)
    params = _random_params(smplx, seed=3)
    with torch.no_grad():
        ours = smplx(params).vertices[1].numpy()
    pkl = smplx.prox_result(params, 1)
    hands = []
    for side in "lr":
        values = pkl[f"{'left' if side == 'l' else 'right'}_hand_pose"][0]
        assert len(values) == (hand_pca or 45)
        if hand_pca:
            values = values @ data[f"hands_components{side}"][:hand_pca]
        hands.append(values + data[f"hands_mean{side}"])
    read = {"betas": torch.tensor(pkl["betas"]), "expression": torch.tensor(pkl["expression"]),
            "global_orient": torch.tensor(pkl["global_orient"]),
            "body_pose": torch.tensor(pkl["body_pose"]).view(1, 21, 3),
            "jaw_pose": torch.tensor(pkl["jaw_pose"]), "transl": torch.tensor(pkl["transl"])}
    fingers = np.concatenate(hands).reshape(30, 3)
    assert np.abs(_reference_lbs(data, read, 0, fingers) - ours).max() < 1e-4
    exported = smplx.export(params, 1)
    convention = exported["hand_convention"]
    assert not convention["flat_hand_mean"] and convention["pkl_hand_values"] == (hand_pca or 45)
    relative = np.array(exported["left_hand_pose"] + exported["right_hand_pose"])
    assert np.allclose(relative.reshape(2, 45) + np.stack([data["hands_meanl"],
                                                          data["hands_meanr"]]),
                       fingers.reshape(2, 45), atol=1e-5)


def test_genders_load_their_own_file(model_dir, smplx):
    female = SMPLXBody.load(model_dir, "female")
    assert female.gender == "female" and not torch.equal(female.v_template, smplx.v_template)


def test_pickled_extras_in_the_file_are_skipped_not_unpickled(model_dir, tmp_path):
    """The distributed files also hold pickled dicts (joint2num, part2num)."""
    data = dict(np.load(model_dir / "SMPLX_NEUTRAL.npz"))
    data["joint2num"] = np.array({"pelvis": 0}, dtype=object)
    np.savez(tmp_path / "SMPLX_NEUTRAL.npz", **data)
    assert SMPLXBody.load(tmp_path, "neutral").v_template.shape == (10475, 3)


def test_body_segments_become_the_contact_parts(model_dir, tmp_path):
    folder = tmp_path / "body_segments"
    folder.mkdir()
    for i, name in enumerate(smplx_body.SEGMENT_FILES.values()):
        (folder / f"{name}.json").write_text(json.dumps({"verts_ind": [i, i + 100],
                                                         "faces_ind": [0]}))
    body = SMPLXBody.load(model_dir, "neutral", segments=folder)
    assert body.contact_parts["gluteus"].tolist() == [5, 105]
    (folder / "back.json").write_text(json.dumps({"verts_ind": [10 ** 6]}))
    with pytest.raises(InputError, match="back.json: vertex ids outside"):
        SMPLXBody.load(model_dir, "neutral", segments=folder)


def test_derived_contact_parts_are_where_they_belong(smplx):
    v = smplx.v_template
    joints = smplx.J_regressor @ v
    parts = smplx.contact_parts
    assert {"left_hand", "right_hand", "left_foot", "right_foot", "back", "gluteus",
            "thighs"} == set(parts) and all(len(ids) > 0 for ids in parts.values())
    assert (v[parts["left_hand"], 0] > joints[18, 0]).all()  # beyond the left elbow (+x)
    assert (v[parts["left_foot"], 1] < joints[4, 1]).all()  # below the left knee
    assert (v[parts["back"], 2] < joints[3, 2]).all()  # behind the spine


@pytest.mark.parametrize("problem", ["no folder", "no file", "missing array", "wrong shape",
                                     "not npz"])
def test_bad_model_files_are_clear_errors(model_dir, tmp_path, problem):
    folder = tmp_path / "models"
    if problem != "no folder":
        folder.mkdir()
    path = folder / "SMPLX_NEUTRAL.npz"
    data = dict(np.load(model_dir / "SMPLX_NEUTRAL.npz"))
    if problem == "missing array":
        del data["posedirs"]
    if problem == "wrong shape":
        data["J_regressor"] = data["J_regressor"][:54]
    if problem in ("missing array", "wrong shape"):
        np.savez(path, **data)
    if problem == "not npz":
        path.write_bytes(b"not a zip")
    expected = {"no folder": "model folder not found", "no file": "model file not found",
                "missing array": "'posedirs' missing", "wrong shape": "'J_regressor' has shape",
                "not npz": "not a readable .npz"}[problem]
    with pytest.raises(InputError, match=expected) as error:
        SMPLXBody.load(folder, "neutral")
    assert str(folder) in error.value.path


@pytest.mark.parametrize("prior", ["free", "vposer"])
def test_prox_fit_with_smplx_writes_prox_pickles(model_dir, smplx, vposer_dir, tmp_path,
                                                 prior):
    """Keypoints of a posed synthetic SMPL-X body, fitted by `prox fit --model smplx`
    (with the engine's pose prior or a VPoser snapshot)."""
    from prox_engine import synthetic

    params = smplx.init_params(1)
    params["body_pose"][0, 15, 2] = -0.8  # left shoulder down
    params["body_pose"][0, 16, 2] = 0.8
    params["global_orient"][0] = torch.tensor([np.pi, 0.0, 0.0])  # y up -> camera y down
    params["transl"][0] = torch.tensor([0.0, 0.2, 3.0])
    with torch.no_grad():
        out = smplx(params)
    keypoints = out.keypoints[0].numpy()
    uv = synthetic.project(keypoints)
    conf = np.ones(len(uv))
    conf[FACE] = 0
    data = tmp_path / "data"
    floor = synthetic.open_box([6.0, 6.0, 0.02], [0.0, 0.0, -0.01], bottom=True)
    cam2world = synthetic.look_at(np.array([0.0, -3.0, 1.2]), np.array([0.0, 0.0, 1.0]))
    synthetic.write_scene(data, "Synthetic", floor, cam2world)
    rec, frame = "Synthetic_00000_01", synthetic.frame_name(0)
    synthetic.write_frame(data, rec, frame, [synthetic.openpose_person(uv, conf)],
                          out.vertices[0].numpy(), keypoints[BODY])
    run = subprocess.run([sys.executable, "-m", "prox_engine.cli", "fit", str(data), "--out",
                          str(tmp_path / "out"), "--config", "rgb", "--model", "smplx",
                          "--model-path", str(model_dir),
                          *(["--vposer-path", str(vposer_dir)] if prior == "vposer" else [])],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "out" / rec / "summary.json").read_text())
    # A random VPoser reaches fewer poses than free joint rotations, and PROX's prior
    # weights (404^2 on |z|^2 in the first stages) hold its code near the mean: 83 px.
    limit = 25 if prior == "free" else 100
    assert summary["frames_fitted"] == 1 and summary["reprojection_error_px"] < limit, summary
    assert (tmp_path / "out" / rec / "report" / "images" / f"{frame}_side.jpg").exists()
    with (tmp_path / "out" / rec / "results" / frame / "000.pkl").open("rb") as handle:
        result = pickle.load(handle)
    assert result["body_pose"].shape == (1, 63) and result["betas"].shape == (1, 10)
    assert result["left_hand_pose"].shape == (1, 12) and result["expression"].shape == (1, 10)
    assert result["camera_rotation"].shape == (1, 3, 3)
    assert ("pose_embedding" in result) == (prior == "vposer")
    exported = json.loads((tmp_path / "out" / rec / "results" / frame / "000.json").read_text())
    assert exported["model"] == "smplx" and len(exported["body_pose"]) == 21
    assert np.allclose(result["body_pose"].reshape(21, 3),
                       np.array(list(exported["body_pose"].values())), atol=1e-6)


@pytest.fixture(scope="module")
def vposer_dir(tmp_path_factory):
    """A VPoser v1.0-shaped snapshot with random weights (hidden width 64, not 512) whose
    codes decode to rotations around the rest pose, as a trained prior's do."""
    folder = tmp_path_factory.mktemp("vposer_v1_0")
    g = torch.Generator().manual_seed(0)
    shapes = {name: tuple(64 if s is None else s for s in shape)
              for name, shape in SNAPSHOT_SHAPES.items()}
    state = {name: torch.randn(shape, generator=g) * 0.2 for name, shape in shapes.items()}
    state["bodyprior_dec_out.bias"] = torch.tensor([1.0, 0, 0, 1, 0, 0]).repeat(21)
    for bn in ("bodyprior_enc_bn1", "bodyprior_enc_bn2"):
        state[f"{bn}.running_var"] = state[f"{bn}.running_var"].abs() + 0.5
    (folder / "snapshots").mkdir()
    torch.save(state, folder / "snapshots" / "TR00_E096.pt")
    return folder


def test_vposer_decodes_rotations_and_encodes_postures(vposer_dir):
    vposer = VPoser.load(vposer_dir)
    rotations = vposer.decode(torch.randn(3, 32))
    assert rotations.shape == (3, 21, 3, 3)
    eye = torch.eye(3).expand(3, 21, 3, 3)
    assert torch.allclose(rotations @ rotations.transpose(-1, -2), eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(3, 21), atol=1e-5)
    assert vposer.encode(torch.zeros(2, 21, 3)).shape == (2, 32)


def test_smplx_with_vposer_fits_a_code(model_dir, vposer_dir):
    body = SMPLXBody.load(model_dir, "neutral", vposer=vposer_dir)
    plain = SMPLXBody.load(model_dir, "neutral")
    assert body.pose_group() == ["pose_embedding"] and plain.pose_group() == ["body_pose"]
    params = body.init_params(1, "sitting")
    assert "body_pose" not in params and params["pose_embedding"].abs().sum() > 0
    params["pose_embedding"] = torch.randn(1, 32)
    assert torch.isclose(body.pose_prior(params), (params["pose_embedding"] ** 2).sum())
    decoded = body.body_pose(params)
    with torch.no_grad():
        ours = body(params).vertices
        theirs = plain({**{k: v for k, v in params.items() if k != "pose_embedding"},
                        "body_pose": decoded}).vertices
    assert torch.allclose(ours, theirs, atol=1e-5)
    result = body.prox_result(params, 0)
    assert result["pose_embedding"].shape == (1, 32)
    assert np.allclose(result["body_pose"], decoded.reshape(1, 63).numpy())


@pytest.mark.parametrize("problem", ["missing weight", "not torch", "no snapshot"])
def test_bad_vposer_snapshots_are_clear_errors(vposer_dir, tmp_path, problem):
    folder = tmp_path / "vposer"
    (folder / "snapshots").mkdir(parents=True)
    state = torch.load(next((vposer_dir / "snapshots").glob("*.pt")), weights_only=True)
    if problem == "missing weight":
        del state["bodyprior_dec_out.weight"]
        torch.save(state, folder / "snapshots" / "a.pt")
    if problem == "not torch":
        (folder / "snapshots" / "a.pt").write_text("hello")
    expected = {"missing weight": "'bodyprior_dec_out.weight' missing",
                "not torch": "not a readable PyTorch state dict",
                "no snapshot": "no VPoser snapshot"}[problem]
    with pytest.raises(InputError, match=expected):
        VPoser.load(folder)


def test_smplx_resolves_its_own_configurations_with_prox_weights(smplx):
    """`rgb`, `prox`, `smplifyd` and `proxd` resolve to SMPL-X's own files for SMPL-X (and
    stay ours for anny), and their prior weights enter the loss squared, as PROX's: the
    first stage's pose prior weighs 404^2 = 163216 times the prior."""
    from prox_engine.config import load_config
    from prox_engine.fitting import Fitter

    for name in ("rgb", "prox", "smplifyd", "proxd"):
        assert load_config(name, "smplx").name == f"smplx-{name}"
        assert load_config(name).name == name
    config = load_config("prox", "smplx")
    assert len(config.stages) == 7 and config.stages[4].weights["face"] == 2
    params = _random_params(smplx)
    camera = Camera(1000.0, 1000.0, 960.0, 540.0)
    fitter = Fitter(smplx, camera, load_config("rgb", "smplx"))
    with torch.no_grad():
        out = smplx(params)
        target, conf = torch.zeros(2, N_KEYPOINTS, 2), torch.ones(2, N_KEYPOINTS)
        terms = fitter._terms(fitter.config.stages[0], params, target, conf, [None], None)(out)
    assert torch.allclose(terms["pose_prior"], 404.0 ** 2 * smplx.pose_prior(params))
    assert torch.allclose(terms["shape"], 100.0 ** 2 * smplx.shape_prior(params))


def test_smplx_fit_with_prox_weights_converges(smplx):
    """A posed synthetic SMPL-X body (face and hands seen) fitted with PROX's weights: no
    stage meets non-finite values and the keypoints are reached within a few pixels
    (a prior this strong keeps a clean synthetic fit 1-2 px above the weaker anny weights:
    measured 4.9 against 3.7 px)."""
    from prox_engine import metrics
    from prox_engine.config import load_config
    from prox_engine.fitting import Fitter, Frame
    from prox_engine.keypoints import Keypoints

    g = torch.Generator().manual_seed(1)
    params = smplx.init_params(1)
    params["body_pose"] = torch.randn(1, 21, 3, generator=g) * 0.25
    params["body_pose"][0, 15, 2], params["body_pose"][0, 16, 2] = -0.8, 0.8  # arms down
    params["global_orient"][0] = torch.tensor([np.pi, 0.3, 0.0])  # upright, turned
    params["transl"][0] = torch.tensor([0.1, 0.2, 3.0])
    camera = Camera(1000.0, 1000.0, 960.0, 540.0)
    with torch.no_grad():
        truth = smplx(params).keypoints[0]
    data = np.concatenate([camera.project(truth[None])[0].numpy(),
                           np.full((N_KEYPOINTS, 1), 0.9)], 1)
    keypoints = Keypoints(data, True, True)
    result = Fitter(smplx, camera, load_config("rgb", "smplx")).fit([Frame("f", keypoints)])[0]
    assert result.events == []
    error = metrics.reprojection_error(result.keypoints, keypoints, camera, smplx.keypoint_mask)
    assert error < 8.0


def test_smplx_prox_weights_beat_anny_weights_on_noisy_keypoints(smplx):
    """On keypoints as a detector gives them (6 px noise, two joints 40 px off), SMPL-X
    fitted with PROX's stage weights lands nearer the true keypoints than with the weights
    tuned for anny, which SMPL-X used before it had its own configurations. (On clean
    synthetic keypoints the stronger prior is 1-2 px further: see the test above.)
    Measured over ten poses: 6.0 against 9.5 px, 3D joints 194 against 334 mm."""
    from prox_engine.config import load_config
    from prox_engine.fitting import Fitter, Frame
    from prox_engine.keypoints import Keypoints

    camera = Camera(1000.0, 1000.0, 960.0, 540.0)
    mask = smplx.keypoint_mask.bool().numpy()
    errors = {"prox": [], "anny": []}
    for seed in (1, 2, 3):
        g = torch.Generator().manual_seed(seed)
        params = smplx.init_params(1)
        params["body_pose"] = torch.randn(1, 21, 3, generator=g) * 0.25
        params["body_pose"][0, 15, 2], params["body_pose"][0, 16, 2] = -0.8, 0.8
        params["global_orient"][0] = torch.tensor([np.pi, 0.3 * (seed % 3 - 1), 0.0])
        params["transl"][0] = torch.tensor([0.1, 0.2, 3.0])
        with torch.no_grad():
            clean = camera.project(smplx(params).keypoints)[0].numpy()
        rng = np.random.default_rng(seed)
        noisy = clean + rng.normal(0, 6.0, clean.shape)
        noisy[rng.choice(25, 2, replace=False)] += rng.normal(0, 40.0, (2, 2))
        keypoints = Keypoints(np.concatenate([noisy, np.full((N_KEYPOINTS, 1), 0.9)], 1),
                              True, True)
        for name, config in (("prox", load_config("rgb", "smplx")), ("anny", load_config("rgb"))):
            result = Fitter(smplx, camera, config).fit([Frame("f", keypoints)])[0]
            assert result.events == []
            fitted = camera.project(result.keypoints[None])[0].numpy()
            errors[name].append(np.linalg.norm(fitted - clean, axis=1)[mask].mean())
    assert np.mean(errors["prox"]) < np.mean(errors["anny"]) - 1.0, errors
