"""Uploaded zips: what validate_upload accepts and rejects, what extract_upload writes."""
from __future__ import annotations

import io
import json
import stat
import struct
import zipfile
from pathlib import Path

import pytest

from prox_engine.dataset import Recording, list_recordings
from prox_engine.keypoints import load_keypoints
from service.upload import UploadError, UploadLimits, _copy, extract_upload, validate_upload

LIMITS = UploadLimits(max_extracted_bytes=4 << 20, max_entries=100, max_recordings=3,
                      max_frames=10)
PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
       "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
       "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
IDENTITY = json.dumps([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def _people(*people: list[float]) -> str:
    return json.dumps({"people": [{"pose_keypoints_2d": p} for p in people]})


PERSON = [v for i in range(25) for v in (100.0 + i, 200.0, 0.9)]
KEYPOINTS = _people(PERSON)


def _frame(i: int) -> str:
    return f"s001_frame_{i:05d}__00.00.00.000"


def _layout(prefix: str = "", recordings: tuple[str, ...] = ("Room_00",), frames: int = 3,
            depth: int = 0) -> dict[str, str | bytes]:
    """A tiny PROX dataset; frames written in reverse order, ``depth`` frames with PNGs."""
    files: dict[str, str | bytes] = {f"{prefix}calibration/Color.json":
                                     json.dumps({"f": [500, 500], "c": [320, 240]})}
    for rec in recordings:
        scene = rec.split("_")[0]
        files[f"{prefix}scenes/{scene}.ply"] = PLY
        files[f"{prefix}cam2world/{scene}.json"] = IDENTITY
        for i in reversed(range(frames)):
            files[f"{prefix}keypoints/{rec}/{_frame(i)}_keypoints.json"] = KEYPOINTS
        for i in range(depth):
            for kind in ("Depth", "BodyIndex"):
                files[f"{prefix}recordings/{rec}/{kind}/{_frame(i)}.png"] = b"\x89PNG"
    return files


def _zip(path: Path, files: dict[str, str | bytes],
         extra: tuple[tuple[zipfile.ZipInfo | str, bytes], ...] = (),
         method: int = zipfile.ZIP_DEFLATED) -> Path:
    with zipfile.ZipFile(path, "w", method) as archive:
        for name, content in files.items():
            archive.writestr(name, content)
        for info, content in extra:
            archive.writestr(info, content)
    return path


def _patch(path: Path, name: str, offset: int, value: int, fmt: str = "I") -> None:
    """Overwrite a field of ``name``'s central-directory header (offset from its signature)."""
    data = bytearray(path.read_bytes())
    pos = data.find(b"PK\x01\x02")
    while data[pos + 46: pos + 46 + struct.unpack_from("<H", data, pos + 28)[0]] != name.encode():
        pos = data.find(b"PK\x01\x02", pos + 4)
    struct.pack_into(f"<{fmt}", data, pos + offset, value)
    path.write_bytes(data)


def _rejected(path: Path, status: int, file: str | None, text: str, **options) -> UploadError:
    with pytest.raises(UploadError) as err:
        validate_upload(path, options.pop("limits", LIMITS), **options)
    assert (err.value.status, err.value.file) == (status, file), str(err.value)
    assert text in err.value.problem
    assert str(err.value) == (f"{file}: " if file is not None else "") + err.value.problem
    return err.value


def _files_under(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file()}


# --------------------------------------------------------------------------- accepted


def test_valid_upload_at_the_root(tmp_path):
    files = _layout(recordings=("Room_00", "Office_01"))
    summary = validate_upload(_zip(tmp_path / "u.zip", files), LIMITS)
    assert summary.base == ""
    assert summary.recordings == {"Office_01": [_frame(0), _frame(1), _frame(2)],
                                  "Room_00": [_frame(0), _frame(1), _frame(2)]}
    assert summary.frame_count == 6
    assert summary.extracted_bytes == sum(len(c) for c in files.values())
    assert validate_upload(tmp_path / "u.zip", LIMITS, frames=2).recordings == {
        "Office_01": [_frame(0), _frame(1)], "Room_00": [_frame(0), _frame(1)]}


def test_valid_upload_inside_one_folder_ignores_macos_debris(tmp_path):
    files = _layout("mydata/") | {"__MACOSX/mydata/._x": b"junk", "mydata/.DS_Store": b"junk",
                                  "mydata/keypoints/.DS_Store": b"junk"}
    summary = validate_upload(_zip(tmp_path / "u.zip", files), LIMITS, frames=1)
    assert summary.base == "mydata/"
    assert summary.recordings == {"Room_00": [_frame(0)]} and summary.frame_count == 1


def test_frames_with_nobody_detected_are_accepted(tmp_path):
    files = _layout(frames=2)
    files[f"keypoints/Room_00/{_frame(0)}_keypoints.json"] = _people()
    files[f"keypoints/Room_00/{_frame(1)}_keypoints.json"] = _people([0.0] * 75)
    assert validate_upload(_zip(tmp_path / "u.zip", files), LIMITS).frame_count == 2


def test_only_the_fitted_frames_are_parsed(tmp_path):
    files = _layout(frames=2)
    files[f"keypoints/Room_00/{_frame(1)}_keypoints.json"] = "{not json"
    path = _zip(tmp_path / "u.zip", files)
    assert validate_upload(path, LIMITS, frames=1).recordings == {"Room_00": [_frame(0)]}
    _rejected(path, 422, f"keypoints/Room_00/{_frame(1)}_keypoints.json", "not valid JSON")


def test_extract_writes_the_dataset_the_engine_reads(tmp_path):
    files = _layout("mydata/", depth=1) | {"__MACOSX/mydata/._x": b"junk"}
    path = _zip(tmp_path / "u.zip", files)
    summary = validate_upload(path, LIMITS, needs_depth=True, frames=1)
    before = _files_under(tmp_path)
    dest = tmp_path / "job" / "data"
    base = extract_upload(path, dest, LIMITS)
    assert base == (dest / "mydata").resolve()
    written = _files_under(dest)
    assert {p.relative_to(dest).as_posix() for p in written} == set(files) - {
        "__MACOSX/mydata/._x"}
    assert _files_under(tmp_path) - written == before  # nothing written outside dest
    assert (base / "scenes" / "Room.ply").read_text() == PLY
    assert list_recordings(base) == list(summary.recordings)
    rec = Recording(base, "Room_00")
    assert rec.frames()[:1] == summary.recordings["Room_00"]
    assert load_keypoints(rec.keypoint_path(_frame(0))).data[0, 0] == 100.0
    assert rec.depth_paths(_frame(0)) is not None


def test_extract_writes_only_what_the_fit_reads(tmp_path):
    """Files of frames beyond ``frames``, other scenes and stray folders stay packed."""
    files = _layout(depth=3) | {
        "recordings/Room_00/Color/" + _frame(0) + ".jpg": b"jpeg",
        "recordings/Room_00/Color/" + _frame(2) + ".jpg": b"jpeg",
        "recordings/Room_00/Other/" + _frame(0) + ".bin": b"x",
        "scenes/Elsewhere.ply": PLY, "padding/zeros.bin": bytes(1000),
        "sdf/Room.json": "{}", "calibration/IR.json": "{}"}
    path = _zip(tmp_path / "u.zip", files)
    dest = tmp_path / "out"
    extract_upload(path, dest, LIMITS, frames=2)
    written = {p.relative_to(dest).as_posix() for p in _files_under(dest)}
    kept = {name for name in files
            if not name.startswith(("padding/", "scenes/Elsewhere", "recordings/Room_00/Other"))
            and _frame(2) not in name}
    assert written == kept


def test_extract_at_the_root_returns_dest(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout())
    assert extract_upload(path, tmp_path / "out", LIMITS) == (tmp_path / "out").resolve()
    assert (tmp_path / "out" / "calibration" / "Color.json").is_file()


# --------------------------------------------------------------------------- 400


def test_not_a_zip(tmp_path):
    (tmp_path / "a.zip").write_text("hello")
    _rejected(tmp_path / "a.zip", 400, None, "not a valid zip file")
    data = _zip(tmp_path / "u.zip", _layout()).read_bytes()
    (tmp_path / "cut.zip").write_bytes(data[: len(data) // 2])
    _rejected(tmp_path / "cut.zip", 400, None, "not a valid zip file")


@pytest.mark.parametrize("name, problem", [
    ("/etc/passwd", "absolute path"),
    ("C:\\windows\\x", "absolute path"),
    ("C:/windows/x", "absolute path"),
    ("\\\\server\\share\\x", "absolute path"),
    ("../x", "'..'"),
    ("keypoints/../../x", "'..'"),
    ("..\\x", "'..'"),
    ("keypoints\\Room_00\\a_keypoints.json", "backslash"),
    ("keypoints//x", "empty or '.'"),
    ("./keypoints/x", "empty or '.'"),
    ("a" * 256, "longer than 255 bytes"),
])
def test_unsafe_names(tmp_path, name, problem):
    path = _zip(tmp_path / "u.zip", _layout(), extra=((name, b"x"),))
    _rejected(path, 400, name, problem)
    with pytest.raises(UploadError) as err:
        extract_upload(path, tmp_path / "out", LIMITS)
    assert err.value.status == 400 and err.value.file == name
    assert _files_under(tmp_path) == {path}  # checked before writing anything


def test_nul_byte_in_a_name(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(), extra=(("keypoints/evil#name", b"x"),))
    path.write_bytes(path.read_bytes().replace(b"evil#name", b"evil\0name"))
    _rejected(path, 400, "keypoints/evil\0name", "NUL byte")


@pytest.mark.parametrize("mode, problem", [(stat.S_IFLNK | 0o777, "symbolic link"),
                                           (stat.S_IFIFO | 0o644, "only regular files")])
def test_links_and_special_files(tmp_path, mode, problem):
    info = zipfile.ZipInfo("scenes/link.ply")
    info.external_attr = mode << 16
    path = _zip(tmp_path / "u.zip", _layout(), extra=((info, b"/etc/passwd"),))
    _rejected(path, 400, "scenes/link.ply", problem)
    with pytest.raises(UploadError, match=problem):
        extract_upload(path, tmp_path / "out", LIMITS)


def test_encrypted_entry(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout())
    _patch(path, "calibration/Color.json", 8, 0x1, "H")
    _rejected(path, 400, "calibration/Color.json", "encrypted")


@pytest.mark.filterwarnings("ignore:Duplicate name")
def test_duplicates_and_file_folder_clashes(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(), extra=(("scenes/Room.ply", b"x"),))
    _rejected(path, 400, "scenes/Room.ply", "duplicate")
    path = _zip(tmp_path / "v.zip", _layout(), extra=(("scenes/Room.ply/x", b"x"),))
    _rejected(path, 400, "scenes/Room.ply", "both a file and a folder")


def test_damaged_keypoint_entry(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(frames=1))
    name = f"keypoints/Room_00/{_frame(0)}_keypoints.json"
    _patch(path, name, 16, 12345)  # CRC-32
    _rejected(path, 400, name, "damaged or unsupported entry")


# --------------------------------------------------------------------------- 413


def test_too_many_entries_and_too_many_bytes(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(frames=5))
    _rejected(path, 413, None, "8 entries in the zip, over the limit of 7",
              limits=UploadLimits(1 << 20, 7, 3, 10))
    size = sum(len(c) for c in _layout(frames=5).values())
    _rejected(path, 413, None, f"{size} bytes uncompressed, over the limit of {size - 1}",
              limits=UploadLimits(size - 1, 100, 3, 10))
    with pytest.raises(UploadError) as err:
        extract_upload(path, tmp_path / "out", UploadLimits(size - 1, 100, 3, 10))
    assert err.value.status == 413 and not (tmp_path / "out").exists()


def test_unsafe_beats_too_large(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(), extra=(("../x", b"x"),))
    _rejected(path, 400, "../x", "'..'", limits=UploadLimits(1, 1, 1, 1))


def test_compression_ratio_of_a_bomb(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(), extra=(("recordings/z.bin", bytes(2 << 20)),),
                method=zipfile.ZIP_BZIP2)
    _rejected(path, 413, "recordings/z.bin", "compressed more than 1000:1")


def test_compression_ratio_of_many_small_members(tmp_path):
    """Members of 1 MB each stay under the per-member check; the zip's total ratio does
    not (a 1.6 MB upload that would write 1 GB, here scaled down)."""
    zeros = tuple((f"recordings/Room_00/pad/{i}.bin", bytes(1 << 20)) for i in range(8))
    path = _zip(tmp_path / "u.zip", _layout(), extra=zeros)
    _rejected(path, 413, None, "more than 100:1 in all",
              limits=UploadLimits(64 << 20, 100, 3, 10))
    with pytest.raises(UploadError):
        extract_upload(path, tmp_path / "out", UploadLimits(64 << 20, 100, 3, 10))
    assert not (tmp_path / "out").exists()  # refused before writing anything


@pytest.mark.parametrize("name, problem", [
    ("keypoints/Room_00/javascript:alert(document.domain)_keypoints.json", "':'"),
    ("keypoints/Room_00/.._keypoints.json", "'..' is not a file name"),
    ("keypoints/Room_00/._keypoints.json", "'.' is not a file name"),
    ("keypoints/Room_00/_keypoints.json", "'' is not a file name"),
    ("keypoints/Room_00/a\tb_keypoints.json", "control character"),
    ("keypoints/Room:1/" + _frame(0) + "_keypoints.json", "':'"),
])
def test_frame_and_recording_names_must_be_plain_file_names(tmp_path, name, problem):
    """Frame and recording names become folders and report links: a name that is not a
    plain file name is a 400 naming the file, before anything is extracted."""
    path = _zip(tmp_path / "u.zip", _layout(), extra=((name, KEYPOINTS),))
    error = _rejected(path, 400, name if "Room:1" not in name else "keypoints/Room:1/",
                      problem)
    assert ("frame name" if "Room:1" not in name else "recording name") in error.problem


def test_lying_declared_size_cannot_fill_the_disk(tmp_path):
    name = f"recordings/Room_00/Color/{_frame(0)}.jpg"
    path = _zip(tmp_path / "u.zip", _layout(), extra=((name, b"\xff" * (1 << 20)),))
    _patch(path, name, 24, 100)  # declared uncompressed size
    assert validate_upload(path, LIMITS).extracted_bytes < 1 << 20
    with pytest.raises(UploadError) as err:
        extract_upload(path, tmp_path / "out", LIMITS)
    # zipfile yields no more than the declared size, so the lie surfaces as a CRC mismatch
    assert (err.value.status, err.value.file) == (400, name) and "CRC" in err.value.problem
    assert (tmp_path / "out" / name).stat().st_size <= 100


def test_copy_stops_past_the_declared_size_and_the_total():
    member = zipfile.ZipInfo("a.bin")
    member.file_size = 25
    out = io.BytesIO()
    with pytest.raises(UploadError, match="more than its declared 25 bytes") as err:
        _copy([b"x" * 10] * 5, out, member, 0, 1000)
    assert err.value.status == 413 and len(out.getvalue()) <= 25
    out = io.BytesIO()
    with pytest.raises(UploadError, match="more than 100 bytes") as err:
        _copy([b"x" * 10] * 2, out, member, 90, 100)
    assert err.value.status == 413 and len(out.getvalue()) <= 10
    assert _copy([b"x" * 10, b"y" * 15], io.BytesIO(), member, 50, 100) == 75


def test_oversized_keypoint_file(tmp_path):
    files = _layout(frames=1)
    name = f"keypoints/Room_00/{_frame(0)}_keypoints.json"
    files[name] = '{"people": [], "pad": "' + "x" * (16 << 20) + '"}'
    path = _zip(tmp_path / "u.zip", files, method=zipfile.ZIP_STORED)
    _rejected(path, 413, name, "over 16 MB", limits=UploadLimits(32 << 20, 100, 3, 10))


# --------------------------------------------------------------------------- 422


@pytest.mark.parametrize("files, file, text", [
    ({"readme.txt": "hi"}, "keypoints/", "expected keypoints/<recording>/<frame>_keypoints.json"),
    ({"data/readme.txt": "hi", "data/keypoints/": ""}, "data/keypoints/", "expected keypoints/"),
    ({"keypoints/Room_00/readme.txt": "hi"}, "keypoints/Room_00/", "no <frame>_keypoints.json"),
])
def test_no_keypoints(tmp_path, files, file, text):
    _rejected(_zip(tmp_path / "u.zip", files), 422, file, text)


@pytest.mark.parametrize("prefix", ["", "mydata/"])
@pytest.mark.parametrize("missing", ["calibration/Color.json", "scenes/Office.ply",
                                     "cam2world/Office.json"])
def test_missing_shared_files(tmp_path, prefix, missing):
    files = _layout(prefix, recordings=("Office_00", "Room_01"))
    del files[prefix + missing]
    _rejected(_zip(tmp_path / "u.zip", files), 422, prefix + missing, "missing")


def test_too_many_recordings_or_frames(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout(recordings=("A_0", "B_0", "C_0", "D_0")))
    _rejected(path, 422, "keypoints/", "4 recordings, over the limit of 3")
    path = _zip(tmp_path / "v.zip", _layout(recordings=("A_0", "B_0"), frames=6))
    _rejected(path, 422, None, "12 frames to fit, over the limit of 10")
    assert validate_upload(path, LIMITS, frames=5).frame_count == 10
    _rejected(path, 422, None, "'frames' must be a positive integer", frames=0)


def test_depth_frames_needed_by_depth_configs(tmp_path):
    path = _zip(tmp_path / "u.zip", _layout("d/", frames=2, depth=1))
    assert validate_upload(path, LIMITS).frame_count == 2  # not needed by default
    assert validate_upload(path, LIMITS, frames=1, needs_depth=True).frame_count == 1
    _rejected(path, 422, f"d/recordings/Room_00/Depth/{_frame(1)}.png", "Depth/ and BodyIndex/",
              needs_depth=True)
    files = _layout(depth=1)
    del files[f"recordings/Room_00/BodyIndex/{_frame(0)}.png"]
    _rejected(_zip(tmp_path / "v.zip", files), 422,
              f"recordings/Room_00/BodyIndex/{_frame(0)}.png", "missing", needs_depth=True,
              frames=1)


@pytest.mark.parametrize("content, problem", [
    ("{not json", "not valid JSON"),
    (b"\xff\xfe{}", "not valid JSON"),
    ("[" * 100_000, "not valid JSON"),
    (json.dumps({"nobody": []}), "no 'people' list"),
    (_people([1.0] * 74), "must hold 75 numbers"),
    (_people(["a"] * 75), "non-numeric"),
    (_people([float("nan")] * 75), "NaN"),
    (_people([1.0, 1.0, -0.5] * 25), "negative confidences"),
    (json.dumps({"people": [{"pose_keypoints_2d": 5}]}), "must hold 75 numbers"),
])
def test_malformed_keypoint_files(tmp_path, content, problem):
    files = _layout("mydata/", frames=2)
    name = f"mydata/keypoints/Room_00/{_frame(1)}_keypoints.json"
    files[name] = content
    _rejected(_zip(tmp_path / "u.zip", files), 422, name, problem)


def _ply(vertices: str = "0 0 0\n1 0 0\n0 1 0\n", faces: str = "3 0 1 2\n") -> str:
    return (f"ply\nformat ascii 1.0\nelement vertex {vertices.count(chr(10))}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {faces.count(chr(10))}\n"
            "property list uchar int vertex_indices\nend_header\n" + vertices + faces)


@pytest.mark.parametrize("file, content, problem", [
    ("scenes/Room.ply", _ply(faces="3 0 1 1000000000\n"), "index out of range"),
    ("scenes/Room.ply", _ply(faces="3 0 1 -1\n"), "index out of range"),
    ("scenes/Room.ply", _ply(vertices="0 0 0\n1e38 0 0\n0 1 0\n"), "beyond 10000 m"),
    ("scenes/Room.ply", _ply(faces="3 0 1 1\n"), "degenerate"),
    ("scenes/Room.ply", "ply\nformat ascii 1.0\nend_header\n", "no triangles"),
    ("cam2world/Room.json", "[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ("cam2world/Room.json", json.dumps([[1, 0, 0, 1e38], [0, 1, 0, 0], [0, 0, 1, 0],
                                        [0, 0, 0, 1]]), "beyond 10000 m"),
    ("calibration/Color.json", json.dumps({"f": [500, 500]}), "'c'"),
    (f"keypoints/Room_00/{_frame(0)}_keypoints.json",
     _people([v for i in range(25) for v in (1e308, 200.0, 0.9)]), "beyond 1e+06"),
])
def test_shared_files_and_keypoints_the_engine_cannot_use(tmp_path, file, content, problem):
    """What the worker would fail on (or fit into NaN) is a 422 naming the file at upload."""
    path = _zip(tmp_path / "u.zip", _layout() | {file: content})
    _rejected(path, 422, file, problem)
