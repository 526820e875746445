"""Checking an uploaded zip of a PROX-layout dataset, and extracting it safely.

:func:`validate_upload` reads the zip's central directory, the calibration, each scene's mesh
and camera pose, and the keypoint files of the frames to be fitted, never extracting;
:func:`extract_upload` repeats the safety and size checks and writes only the files a fit
reads. A rejection raises :class:`UploadError` with an HTTP status: 400 for a corrupt,
encrypted or unsafe zip (or unsafe recording and frame names), 413 for one too large, 422
for a wrong layout or a file the engine cannot read.
"""
from __future__ import annotations

import lzma
import re
import stat
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from prox_engine.dataset import (KEYPOINT_SUFFIX, Recording, load_calibration,
                                 load_cam2world, load_scene_mesh)
from prox_engine.errors import InputError
from prox_engine.keypoints import parse_people

KEYPOINT_MAX_BYTES = 16 << 20  # the most read of one keypoint file
BOMB_RATIO, BOMB_MIN_BYTES = 1000, 1 << 20  # members over 1 MB compressed more than 1000:1
# ... or a zip of many smaller members: real datasets (PNG, JSON, PLY) pack 1:1 to 20:1.
TOTAL_RATIO = 100
# Per recording and fitted frame, the files of recordings/<rec>/ that a fit or report reads.
FRAME_FOLDERS = ("Depth", "BodyIndex", "Color")
CHUNK = 1 << 20
METHODS = {zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA}
# What reading a damaged or unsupported entry raises (bz2: OSError, a bad local name: ValueError)
DAMAGED = (zipfile.BadZipFile, zlib.error, lzma.LZMAError, EOFError, OSError, ValueError,
           NotImplementedError)
DRIVE = re.compile(r"[A-Za-z]:")
LAYOUT = ("expected keypoints/<recording>/<frame>_keypoints.json, with scenes/<Scene>.ply, "
          "cam2world/<Scene>.json and calibration/Color.json beside keypoints/ (<Scene> is "
          "the recording name up to its first '_'), at the zip's root or inside one folder")


@dataclass(frozen=True)
class UploadLimits:
    max_extracted_bytes: int  # total uncompressed size of all members
    max_entries: int  # number of members in the zip
    max_recordings: int  # recordings per job
    max_frames: int  # frames per job, counted after the `frames` option


@dataclass
class UploadSummary:
    base: str  # prefix of the PROX base inside the zip: '' or e.g. 'mydata/'
    recordings: dict[str, list[str]]  # recording -> sorted frame names that will be fitted
    extracted_bytes: int  # declared total uncompressed size

    @property
    def frame_count(self) -> int:
        return sum(len(frames) for frames in self.recordings.values())


class UploadError(Exception):
    """A rejected upload: HTTP status, the file inside the zip (or None) and the problem."""

    def __init__(self, status: int, file: str | None, problem: str) -> None:
        self.status, self.file, self.problem = status, file, problem
        super().__init__(problem if file is None else f"{file}: {problem}")


def validate_upload(zip_path: Path, limits: UploadLimits, frames: int | None = None,
                    needs_depth: bool = False) -> UploadSummary:
    """Check an upload without extracting it; raise :class:`UploadError` at the first problem.

    Keypoint files are parsed for the frames to be fitted (the first ``frames`` of each
    recording), by the engine's parser; files where nobody was detected pass.
    """
    if frames is not None and frames < 1:
        raise UploadError(422, None, f"'frames' must be a positive integer, got {frames}")
    with _open(zip_path) as archive:
        base, total, members = _scan(archive, limits)
        files = {m.filename for m in members if not m.is_dir()}
        recordings = _recordings([m.filename for m in members], base)
        _check_layout(files, base, recordings)
        if len(recordings) > limits.max_recordings:
            raise UploadError(422, f"{base}keypoints/", f"{len(recordings)} recordings, over "
                                                         f"the limit of {limits.max_recordings}")
        recordings = {rec: names[:frames] for rec, names in recordings.items()}
        count = sum(len(names) for names in recordings.values())
        if count > limits.max_frames:
            raise UploadError(422, None, f"{count} frames to fit, over the limit of "
                                         f"{limits.max_frames} (use 'frames' to fit fewer)")
        if needs_depth:
            _check_depth(files, base, recordings)
        _check_shared(archive, base, recordings)
        for rec, names in recordings.items():
            for frame in names:
                _check_keypoints(archive, f"{base}keypoints/{rec}/{frame}{KEYPOINT_SUFFIX}")
    return UploadSummary(base, recordings, total)


def extract_upload(zip_path: Path, dest: Path, limits: UploadLimits,
                   frames: int | None = None) -> Path:
    """Extract the files a fit of the first ``frames`` frames of each recording reads
    (:func:`_read_by_fit`) under ``dest``; return the PROX base folder in it.

    The member and size checks are repeated first. Existing files are never overwritten
    (``dest`` should be new); after an error ``dest`` may hold some of the files.
    """
    dest = Path(dest).resolve()
    with _open(zip_path) as archive:
        base, _, members = _scan(archive, limits)
        recordings = _recordings([m.filename for m in members], base)
        wanted = _read_by_fit(base, {rec: names[:frames] for rec, names in recordings.items()})
        total = 0
        for member in members:
            if member.is_dir() or not wanted(member.filename):
                continue
            target = (dest / member.filename).resolve()
            if target == dest or not target.is_relative_to(dest):
                raise UploadError(400, member.filename, "extracts outside the destination")
            target.parent.mkdir(parents=True, exist_ok=True)
            with open(target, "xb") as out, closing(_chunks(archive, member)) as chunks:
                total = _copy(chunks, out, member, total, limits.max_extracted_bytes)
    return dest / base


def _open(zip_path: Path) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, EOFError, ValueError, NotImplementedError) as exc:
        raise UploadError(400, None, f"not a valid zip file ({exc})") from exc


def _scan(archive: zipfile.ZipFile, limits: UploadLimits
          ) -> tuple[str, int, list[zipfile.ZipInfo]]:
    """The 400 and 413 checks; the base prefix, declared size and members that matter."""
    infos = archive.infolist()
    _check_members(infos)
    if len(infos) > limits.max_entries:
        raise UploadError(413, None, f"{len(infos)} entries in the zip, over the limit of "
                                     f"{limits.max_entries}")
    total = sum(info.file_size for info in infos)
    if total > limits.max_extracted_bytes:
        raise UploadError(413, None, f"{total} bytes uncompressed, over the limit of "
                                     f"{limits.max_extracted_bytes}")
    for info in infos:
        if info.file_size > BOMB_MIN_BYTES and info.file_size > BOMB_RATIO * info.compress_size:
            raise UploadError(413, info.filename, f"compressed more than {BOMB_RATIO}:1 "
                                                  "(a zip bomb?)")
    packed = sum(info.compress_size for info in infos)
    if total > BOMB_MIN_BYTES and total > TOTAL_RATIO * packed:
        raise UploadError(413, None, f"{total} bytes uncompressed from {packed} compressed, "
                                     f"more than {TOTAL_RATIO}:1 in all (a zip bomb?)")
    members = [info for info in infos if not _ignored(info.filename)]
    return _base([m.filename for m in members]), total, members


def _check_members(infos: list[zipfile.ZipInfo]) -> None:
    """400 for unsafe names, encryption, unknown methods, links, duplicates and clashes."""
    seen: set[str] = set()
    files: set[str] = set()
    folders: set[str] = set()
    for info in infos:
        name = info.orig_filename  # ``filename`` is cut at a NUL byte
        problem = _name_problem(name)
        if problem:
            raise UploadError(400, name, f"unsafe name: {problem}")
        if info.flag_bits & 0x1:
            raise UploadError(400, name, "encrypted entries are not supported")
        if info.compress_type not in METHODS:
            raise UploadError(400, name, f"unsupported compression method {info.compress_type}")
        kind = stat.S_IFMT(info.external_attr >> 16)
        if kind == stat.S_IFLNK:
            raise UploadError(400, name, "symbolic links are not allowed")
        if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
            raise UploadError(400, name, "only regular files and folders are allowed")
        if name in seen:
            raise UploadError(400, name, "duplicate entry")
        seen.add(name)
        parts = name.removesuffix("/").split("/")
        folders.update("/".join(parts[:i]) for i in range(1, len(parts)))
        (folders if info.is_dir() else files).add("/".join(parts))
    if clash := files & folders:
        raise UploadError(400, min(clash), "both a file and a folder")


def _name_problem(name: str) -> str | None:
    if "\0" in name:
        return "NUL byte"
    path = name.replace("\\", "/")
    if path.startswith("/") or DRIVE.match(path):
        return "absolute path"
    parts = path.removesuffix("/").split("/")
    if ".." in parts:
        return "'..' in the path"
    if "\\" in name:
        return "backslash (zip paths use '/')"
    if "" in parts or "." in parts:
        return "empty or '.' path component"
    if any(len(part.encode()) > 255 for part in parts):
        return "path component longer than 255 bytes"
    return None


def _plain_name_problem(name: str) -> str | None:
    """Why a recording or frame name is not a plain file name (it names result folders
    and report pages, and is linked from them), or None."""
    if name in ("", ".", ".."):
        return f"'{name}' is not a file name"
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        return "contains a control character"
    if bad := sorted(set(name) & set(':/\\')):
        return f"contains {' '.join(repr(c) for c in bad)}"
    return None


def _ignored(name: str) -> bool:
    """macOS debris: ``__MACOSX/`` and ``.DS_Store``."""
    return name.startswith("__MACOSX/") or name.removesuffix("/").split("/")[-1] == ".DS_Store"


def _base(names: list[str]) -> str:
    """'' when the layout is at the root, 'X/' when every entry is inside one folder X."""
    tops = {name.split("/", 1)[0] for name in names}
    if len(tops) == 1 and "keypoints" not in tops:
        top = f"{tops.pop()}/"
        if all(name.startswith(top) for name in names):
            return top
    return ""


def _recordings(names: list[str], base: str) -> dict[str, list[str]]:
    """Recording -> sorted frame names, for every folder under ``keypoints/``."""
    prefix = f"{base}keypoints/"
    recordings: dict[str, list[str]] = {}
    for name in names:
        if not name.startswith(prefix):
            continue
        rec, slash, rest = name[len(prefix):].partition("/")
        if not slash:
            continue
        if problem := _plain_name_problem(rec):
            raise UploadError(400, f"{prefix}{rec}/", f"recording name {problem}")
        frames = recordings.setdefault(rec, [])
        if rest.endswith(KEYPOINT_SUFFIX) and "/" not in rest:
            frame = rest.removesuffix(KEYPOINT_SUFFIX)
            if problem := _plain_name_problem(frame):
                raise UploadError(400, name, f"frame name {problem}")
            frames.append(frame)
    return {rec: sorted(frames) for rec, frames in sorted(recordings.items())}


def _check_layout(files: set[str], base: str, recordings: dict[str, list[str]]) -> None:
    if not recordings:
        raise UploadError(422, f"{base}keypoints/", f"no recordings found: {LAYOUT}")
    for rec, frames in recordings.items():
        if not frames:
            raise UploadError(422, f"{base}keypoints/{rec}/",
                              f"no <frame>{KEYPOINT_SUFFIX} files in this recording")
    for name in _shared_files(base, recordings):
        if name not in files:
            raise UploadError(422, name, f"missing: {LAYOUT}")


def _shared_files(base: str, recordings: Iterable[str]
                  ) -> dict[str, Callable[[Path, bytes], object]]:
    """The files every fit of these recordings needs besides its frames (calibration, each
    scene's mesh and camera pose), with the engine's reader of each."""
    files: dict[str, Callable[[Path, bytes], object]] = {
        f"{base}calibration/Color.json": load_calibration}
    for rec in recordings:
        scene = Recording(Path(base), rec).scene_name
        files[f"{base}scenes/{scene}.ply"] = load_scene_mesh
        files[f"{base}cam2world/{scene}.json"] = load_cam2world
    return files


def _read_by_fit(base: str, recordings: dict[str, list[str]]) -> Callable[[str], bool]:
    """Whether a member is read when fitting these recordings' frames and reporting on
    them: calibration, each scene's mesh, camera pose and PROX SDF, and per frame its
    keypoints and its depth, body-mask and colour images."""
    shared = {f"{base}calibration/", *_shared_files(base, recordings)}
    frame_files: set[str] = set()
    for rec, frames in recordings.items():
        scene = Recording(Path(base), rec).scene_name
        shared |= {f"{base}sdf/{scene}.json", f"{base}sdf/{scene}_sdf.npy"}
        for frame in frames:
            frame_files.add(f"{base}keypoints/{rec}/{frame}{KEYPOINT_SUFFIX}")
            frame_files |= {f"{base}recordings/{rec}/{kind}/{frame}" for kind in FRAME_FOLDERS}

    def wanted(name: str) -> bool:
        folder, _, file = name.rpartition("/")
        return (name in shared or f"{folder}/" in shared or name in frame_files
                or f"{folder}/{file.rsplit('.', 1)[0]}" in frame_files)

    return wanted


def _check_depth(files: set[str], base: str, recordings: dict[str, list[str]]) -> None:
    for rec, frames in recordings.items():
        for frame in frames:
            for kind in ("Depth", "BodyIndex"):
                name = f"{base}recordings/{rec}/{kind}/{frame}.png"
                if name not in files:
                    raise UploadError(422, name, "missing: this configuration fits depth, which "
                                                 "needs Depth/ and BodyIndex/ PNGs of every "
                                                 "fitted frame")


def _check_shared(archive: zipfile.ZipFile, base: str, recordings: dict[str, list[str]]
                  ) -> None:
    """422 unless the engine reads the calibration and each scene's mesh and camera pose
    (face indices in range, finite and sane coordinates, a rigid pose)."""
    for name, load in _shared_files(base, recordings).items():
        try:
            load(Path(name), _read(archive, name))
        except InputError as exc:
            raise UploadError(422, name, exc.problem) from exc


def _check_keypoints(archive: zipfile.ZipFile, name: str) -> None:
    """422 unless the engine parses the file; nobody detected is fine."""
    content = _read(archive, name, KEYPOINT_MAX_BYTES)
    try:
        parse_people(content, name)
    except InputError as exc:
        raise UploadError(422, name, exc.problem) from exc


def _read(archive: zipfile.ZipFile, name: str, limit: int | None = None) -> bytes:
    """A member's bytes (400 when damaged; 413 past ``limit``)."""
    try:
        with archive.open(name) as member:
            content = member.read(-1 if limit is None else limit + 1)
    except DAMAGED as exc:
        raise UploadError(400, name, f"damaged or unsupported entry ({exc})") from exc
    if limit is not None and len(content) > limit:
        raise UploadError(413, name, f"file over {limit >> 20} MB, the most read of its kind")
    return content


def _chunks(archive: zipfile.ZipFile, member: zipfile.ZipInfo) -> Iterator[bytes]:
    """The member's decompressed bytes; a damaged member is a 400."""
    try:
        with archive.open(member) as source:
            while chunk := source.read(CHUNK):
                yield chunk
    except DAMAGED as exc:
        raise UploadError(400, member.filename, f"damaged or unsupported entry ({exc})") from exc


def _copy(chunks: Iterable[bytes], out: BinaryIO, member: zipfile.ZipInfo, total: int,
          limit: int) -> int:
    """Write ``chunks`` to ``out``, stopping (413) past the member's declared size or past
    ``limit`` bytes extracted in all (``total`` so far); return the new total."""
    written = 0
    for chunk in chunks:
        written += len(chunk)
        if written > member.file_size:
            raise UploadError(413, member.filename, f"decompresses to more than its declared "
                                                    f"{member.file_size} bytes")
        if total + written > limit:
            raise UploadError(413, None, f"the files decompress to more than {limit} bytes")
        out.write(chunk)
    return total + written
