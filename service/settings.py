"""Service configuration from environment variables, shared by the API and the workers."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from prox_engine.assets import home

if TYPE_CHECKING:
    from .upload import UploadLimits


def _number(name: str, default: int | float) -> int | float:
    """An environment variable of the default's type; unset or empty gives the default."""
    value = os.environ.get(name)
    if value is None or value == "":
        return default
    try:
        return type(default)(value)
    except ValueError as exc:
        raise ValueError(f"environment variable {name}={value!r} is not a "
                         f"{type(default).__name__}") from exc


def parse_tokens(spec: str) -> dict[str, str]:
    """``name:token`` pairs separated by commas or newlines (``name token`` also works)
    -> {token: name}."""
    tokens: dict[str, str] = {}
    for item in spec.replace(",", "\n").splitlines():
        item = item.strip()
        if not item or item.startswith("#"):
            continue
        name, sep, token = item.replace(" ", ":", 1).partition(":")
        name, token = name.strip(), token.strip()
        if not sep or not name or len(token) < 8:
            raise ValueError(f"bad API token entry {item.split(':')[0]!r}: expected "
                             "'name:token' with a token of at least 8 characters")
        tokens[token] = name
    return tokens


@dataclass(frozen=True)
class Settings:
    """Everything an operator configures (``PROX_*`` environment variables)."""

    redis_url: str = "redis://127.0.0.1:6379/0"
    storage_dir: Path = field(default_factory=lambda: home() / "storage")
    tokens: dict[str, str] = field(default_factory=dict)  # token -> owner name
    queue: str = "prox"
    max_upload_bytes: int = 512 << 20
    max_extracted_bytes: int = 4096 << 20
    max_entries: int = 200_000
    max_frames: int = 5000
    max_recordings: int = 20
    stale_after_s: int = 60  # a running job without a heartbeat this long has lost its worker
    max_attempts: int = 2  # a job whose worker died is retried once
    reap_interval_s: float = 5.0
    job_timeout_s: int = 600  # plus seconds_per_frame_limit per frame
    model_dir: Path | None = None  # licensed SMPLX_*.npz (+ body_segments/), mounted read-only
    seconds_per_frame_limit: int = 120

    def upload_limits(self) -> UploadLimits:
        from .upload import UploadLimits

        return UploadLimits(self.max_extracted_bytes, self.max_entries, self.max_recordings,
                            self.max_frames)

    @classmethod
    def from_env(cls) -> Settings:
        tokens_spec = os.environ.get("PROX_API_TOKENS", "")
        tokens_file = os.environ.get("PROX_TOKENS_FILE")
        if tokens_file:
            tokens_spec += "\n" + Path(tokens_file).read_text()
        return cls(
            redis_url=os.environ.get("PROX_REDIS_URL", cls.redis_url),
            storage_dir=Path(os.environ.get("PROX_STORAGE_DIR") or home() / "storage")
            .absolute(),
            tokens=parse_tokens(tokens_spec),
            queue=os.environ.get("PROX_QUEUE", cls.queue),
            max_upload_bytes=_number("PROX_MAX_UPLOAD_MB", cls.max_upload_bytes >> 20) << 20,
            max_extracted_bytes=_number("PROX_MAX_EXTRACTED_MB",
                                     cls.max_extracted_bytes >> 20) << 20,
            max_frames=_number("PROX_MAX_FRAMES", cls.max_frames),
            max_recordings=_number("PROX_MAX_RECORDINGS", cls.max_recordings),
            stale_after_s=_number("PROX_JOB_STALE_S", cls.stale_after_s),
            max_attempts=_number("PROX_JOB_ATTEMPTS", cls.max_attempts),
            reap_interval_s=_number("PROX_REAP_INTERVAL_S", cls.reap_interval_s),
            job_timeout_s=_number("PROX_JOB_TIMEOUT_S", cls.job_timeout_s),
            model_dir=Path(os.environ["PROX_MODEL_DIR"]).absolute()
            if os.environ.get("PROX_MODEL_DIR") else None,
        )
