"""Job file storage behind a small object-store interface.

Keys are ``/``-separated paths such as ``jobs/<id>/upload.zip``. :class:`LocalStorage` keeps
them under a directory; several nodes share it by mounting the same directory (NFS, EFS,
CephFS) at ``PROX_STORAGE_DIR``. An S3-compatible store maps one to one: ``put_file`` is
``put_object``, ``put_tree`` uploads the objects before the job is marked finished (readers
only look once it is), ``open`` is ``get_object``, ``delete_prefix`` is ``delete_objects``.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import uuid
import zipfile
from abc import ABC, abstractmethod
from pathlib import Path
from stat import S_ISREG
from typing import BinaryIO, Iterator


class Storage(ABC):
    """Where uploads and results live, readable by the API and every worker."""

    @abstractmethod
    def put_file(self, key: str, src: Path) -> None:
        """Store a local file under ``key``, atomically (readers see all or nothing)."""

    @abstractmethod
    def put_tree(self, prefix: str, src: Path) -> None:
        """Store a local directory's files under ``prefix/``, replacing what was there."""

    @abstractmethod
    def get_file(self, key: str, dest: Path) -> None:
        """Copy ``key`` to a local file (raises ``FileNotFoundError``)."""

    @abstractmethod
    def open(self, key: str) -> BinaryIO:
        """Open ``key`` for reading (raises ``FileNotFoundError``)."""

    def chunks(self, key: str, size: int = 1 << 20) -> Iterator[bytes]:
        """The content of ``key`` in pieces, for streaming responses."""
        with self.open(key) as handle:
            while chunk := handle.read(size):
                yield chunk

    @abstractmethod
    def size(self, key: str) -> int | None:
        """Size in bytes, or None when ``key`` does not exist."""

    @abstractmethod
    def delete_prefix(self, prefix: str) -> None:
        """Delete every key under ``prefix/``."""

    @abstractmethod
    def folders(self, prefix: str) -> list[tuple[str, float]]:
        """The names directly under ``prefix/`` that hold keys, with when each last
        changed (seconds since the epoch)."""


def _check_key(key: str) -> str:
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"invalid storage key {key!r}")
    return key


class LocalStorage(Storage):
    """A directory on a local or shared file system."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def put_file(self, key: str, src: Path) -> None:
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
        os.close(fd)
        try:
            shutil.copyfile(src, tmp)
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    def put_tree(self, prefix: str, src: Path) -> None:
        # Copy beside the target, then swap directories with renames.
        target = self.path(prefix)
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = target.with_name(f".{target.name}.{uuid.uuid4().hex}")
        old = target.with_name(f".{target.name}.old.{uuid.uuid4().hex}")
        try:
            shutil.copytree(src, staging)
            if target.exists():
                os.replace(target, old)
            os.replace(staging, target)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
            shutil.rmtree(old, ignore_errors=True)

    def get_file(self, key: str, dest: Path) -> None:
        shutil.copyfile(self.path(key), dest)

    def open(self, key: str) -> BinaryIO:
        return self.path(key).open("rb")

    def size(self, key: str) -> int | None:
        path = self.path(key)
        try:
            stat = path.stat()
        except (OSError, ValueError):  # missing, or a name no file can have (too long, NUL)
            return None
        return stat.st_size if S_ISREG(stat.st_mode) else None

    def delete_prefix(self, prefix: str) -> None:
        shutil.rmtree(self.path(prefix), ignore_errors=True)

    def folders(self, prefix: str) -> list[tuple[str, float]]:
        folder = self.path(prefix)
        return ([(p.name, p.stat().st_mtime) for p in folder.iterdir() if p.is_dir()]
                if folder.is_dir() else [])


COMPRESSED = {".jpg", ".jpeg", ".png", ".mp4", ".zip"}  # stored as they are


def zip_tree(src: Path, archive: Path) -> None:
    """Write a directory's files to a zip, with paths relative to ``src``: deflated at the
    fastest level (level 6 took 1.6 times as long for 1 % less on a job's results), files
    that are compressed already stored."""
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for path in sorted(Path(src).rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(src).as_posix(),
                         zipfile.ZIP_STORED if path.suffix.lower() in COMPRESSED else None)
