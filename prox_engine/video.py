"""The report's video: H.264 MP4, one video frame per rendered frame, the views side by side.

opencv-python-headless's wheels carry no H.264 encoder (a licensing choice), so the video
goes through imageio-ffmpeg, whose wheel bundles an ffmpeg built with libx264; MP4 with
H.264 in yuv420p and the index up front ("faststart") plays in every browser, from disk too.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

TILE = (640, 360)  # each view's size in the video


class VideoWriter:
    """Streams frames (a list of same-sized views each) to ``path``; use as a context."""

    def __init__(self, path: Path, fps: float, tile: tuple[int, int] = TILE) -> None:
        self.path, self.fps, self.tile = Path(path), fps, tile
        self._partial = self.path.with_name(f".{self.path.stem}.part{self.path.suffix}")
        self.frames = 0
        self._writer = None  # ffmpeg, started by the first frame (which sets the width)

    def add(self, views: list[np.ndarray]) -> None:
        """One video frame: ``views`` (H, W, 3) uint8, resized to the tile and side by side."""
        from PIL import Image

        if self._writer is None:
            import imageio_ffmpeg

            self._writer = imageio_ffmpeg.write_frames(
                str(self._partial), (self.tile[0] * len(views), self.tile[1]), fps=self.fps,
                codec="libx264", pix_fmt_out="yuv420p", macro_block_size=8, quality=None,
                ffmpeg_log_level="error",
                output_params=["-crf", "23", "-preset", "veryfast", "-movflags", "+faststart"])
            self._writer.send(None)  # start ffmpeg
        tiles = [np.asarray(Image.fromarray(v[..., :3]).resize(self.tile, Image.BILINEAR))
                 for v in views]
        self._writer.send(np.ascontiguousarray(np.concatenate(tiles, axis=1)))
        self.frames += 1

    def close(self, keep: bool = True) -> None:
        """Finish the file and put it in place (``keep``, and any frame), or throw it away."""
        if self._writer is None:
            return
        self._writer.close()
        if keep:
            os.replace(self._partial, self.path)
        else:
            self._partial.unlink(missing_ok=True)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, kind: type | None, *exc: object) -> None:
        self.close(keep=kind is None)
