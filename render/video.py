"""Frames -> MP4 (H.264, yuv420p: plays in browsers and every player) with imageio-ffmpeg's
bundled ffmpeg, and what a written video holds (frame count and size, read back with OpenCV).

H.264 in yuv420p needs even frame sizes: an odd width or height is padded by one pixel
(the last column/row repeated). The file is written atomically (a temporary file renamed at the
end), frames are streamed (not kept in memory).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import cv2
import numpy as np

from render.errors import SineError
from render.io import atomic_path


def to_uint8(frame: np.ndarray) -> np.ndarray:
    """float RGB in [0, 1] (or uint8) [H, W, 3] -> uint8 [H, W, 3]."""
    frame = np.asarray(frame)
    if frame.dtype != np.uint8:
        frame = (np.clip(frame, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if frame.ndim == 2:
        frame = np.repeat(frame[..., None], 3, axis=2)
    return np.ascontiguousarray(frame[..., :3])


def even_size(width: int, height: int) -> tuple[int, int]:
    return width + width % 2, height + height % 2


class VideoWriter:
    """`with VideoWriter(path, fps) as video: video.write(frame)`; frames [H, W, 3] of one size."""

    def __init__(self, path: str | Path, fps: float = 24.0):
        self.path = Path(path)
        self.fps = float(fps)
        self.size: tuple[int, int] | None = None  # (width, height) of the first frame
        self.frames = 0
        self._stack = contextlib.ExitStack()
        self._gen = None

    def __enter__(self) -> VideoWriter:
        if self.path.suffix.lower() != ".mp4":
            raise SineError(f"{self.path}: videos are written as .mp4")
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        return self

    def write(self, frame: np.ndarray) -> None:
        frame = to_uint8(frame)
        h, w = frame.shape[:2]
        if self.size is None:
            import imageio_ffmpeg

            self.size = (w, h)
            self._gen = imageio_ffmpeg.write_frames(
                str(self._tmp),
                even_size(w, h),
                fps=self.fps,
                codec="libx264",
                pix_fmt_out="yuv420p",
                macro_block_size=1,
                ffmpeg_log_level="error",
            )
            self._gen.send(None)
        elif (w, h) != self.size:
            raise SineError(f"video frames must all be {self.size[0]}x{self.size[1]}, got {w}x{h}")
        ew, eh = even_size(w, h)
        if (ew, eh) != (w, h):
            frame = np.pad(frame, ((0, eh - h), (0, ew - w), (0, 0)), mode="edge")
        self._gen.send(np.ascontiguousarray(frame))
        self.frames += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self._gen is not None:
                self._gen.close()
            if exc_type is None and self.frames == 0:
                raise SineError(f"{self.path}: no frames to write")
        except BaseException as err:  # removes the temporary file
            self._stack.__exit__(type(err), err, err.__traceback__)
            raise
        self._stack.__exit__(exc_type, exc, tb)


def write_video(path: str | Path, frames, fps: float = 24.0) -> None:
    """Writes an iterable of frames [H, W, 3] (float in [0, 1] or uint8) as an MP4."""
    with VideoWriter(path, fps) as video:
        for frame in frames:
            video.write(frame)


def video_info(path: str | Path) -> dict:
    """{"frames": decoded frame count, "width", "height", "fps"} of a video (OpenCV)."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise SineError(f"{path} cannot be opened as a video")
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        n, size = 0, (0, 0)
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            n += 1
            size = (frame.shape[1], frame.shape[0])
    finally:
        cap.release()
    return {"frames": n, "width": size[0], "height": size[1], "fps": fps}
