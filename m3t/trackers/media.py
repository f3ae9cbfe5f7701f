"""Decoding a clip's media for the 2D trackers: a video file or a folder of frame images -> RGB frames.

Frames are streamed one at a time (a long video is never held in memory). Opening is eager: a missing
file, a video that decodes no frame or an unreadable first image fail in :func:`open_media` with a
:class:`MediaError` that names the file, so a corpus run can quarantine the clip before tracking starts;
an unreadable image later in a folder raises the same error while iterating.

Frame folders hold ``.png`` / ``.jpg`` / ``.jpeg`` files ordered by the last integer in their name
(``frame_2.png`` before ``frame_10.png``) when every name has one, else by name.

Axis legend: H height, W width (pixels); frames are (H, W, 3) uint8 RGB.
"""
from __future__ import annotations

import os
import re
import struct
from collections.abc import Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_PIXELS_ENV = "M3T_MAX_IMAGE_PIXELS"
MAX_PIXELS = 2**26  # 67 megapixels a frame; 8K UHD is 33


class MediaError(ValueError):
    """Media that cannot be decoded; the message names the file and what to do."""


@dataclass(frozen=True)
class MediaInfo:
    path: Path
    kind: Literal["video", "frames"]
    fps: float
    width: int
    height: int
    num_frames: int | None  # frame folders: exact; videos: the container's count (may be approximate), None if unknown


@dataclass(frozen=True)
class MediaStream:
    """An opened clip: what it is, and its frames as a one-pass generator of (H, W, 3) uint8 RGB arrays
    (``frames.close()`` releases the decoder early)."""

    info: MediaInfo
    frames: Generator[np.ndarray, None, None]


def _frame_number(name: str) -> int | None:
    found = re.findall(r"\d+", Path(name).stem)
    return int(found[-1]) if found else None


def list_frame_files(folder: str | Path) -> list[Path]:
    """The images of a frame folder in playback order (see the module docstring)."""
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if all(_frame_number(p.name) is not None for p in files):
        return sorted(files, key=lambda p: (_frame_number(p.name), p.name))
    return sorted(files, key=lambda p: p.name)


def declared_image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) a PNG or JPEG header declares, read without decoding; None for another format or a header
    this reader cannot follow (the decoder then judges the file)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if data[:2] != b"\xff\xd8":
        return None
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            at += 2
            continue
        (length,) = struct.unpack(">H", data[at + 2:at + 4])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and at + 9 <= len(data):
            height, width = struct.unpack(">HH", data[at + 5:at + 9])
            return width, height
        at += 2 + length
    return None


def check_pixels(width: int, height: int, where: str) -> None:
    """Refuse a frame whose declared size passes ``M3T_MAX_IMAGE_PIXELS`` (default :data:`MAX_PIXELS`) before a
    decoder allocates it (OpenCV allows 2^30 pixels: 3 GB for one frame a 1 kB file declares)."""
    limit = int(os.environ.get(MAX_PIXELS_ENV) or MAX_PIXELS)
    if width * height > limit:
        raise MediaError(f"{where} declares {width}x{height} pixels, more than {limit:,}; a legitimately large frame: "
                         f"raise {MAX_PIXELS_ENV}")


def read_image_rgb(path: str | Path) -> np.ndarray:
    """One image file -> (H, W, 3) uint8 RGB (grey and RGBA images are converted)."""
    path = Path(path)
    # imdecode on the bytes instead of imread: imread cannot open non-ASCII paths on every platform.
    data = np.fromfile(path, dtype=np.uint8) if path.is_file() else np.empty(0, np.uint8)
    size = declared_image_size(data[: 1 << 16].tobytes())  # the header only, not a copy of the file
    if size is not None:
        check_pixels(*size, f"frame image {path}")
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if bgr is None:
        raise MediaError(f"frame image {path} is missing or unreadable (not a decodable PNG/JPEG); "
                         "replace or remove it, or quarantine the clip")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _open_folder(folder: Path, fps: float | None) -> MediaStream:
    files = list_frame_files(folder)
    if not files:
        raise MediaError(f"frame folder {folder} holds no {'/'.join(IMAGE_SUFFIXES)} images")
    if fps is None or not fps > 0:
        raise MediaError(f"frame folder {folder} has no frame rate of its own; pass fps= (the corpus' rate)")
    first = read_image_rgb(files[0])
    height, width = first.shape[:2]

    def frames() -> Generator[np.ndarray, None, None]:
        yield first
        for path in files[1:]:
            image = read_image_rgb(path)
            if image.shape[:2] != (height, width):
                raise MediaError(f"frame image {path} is {image.shape[1]}x{image.shape[0]}, the folder's first "
                                 f"frame {files[0].name} is {width}x{height}; all frames of a clip must match")
            yield image

    return MediaStream(MediaInfo(folder, "frames", float(fps), width, height, len(files)), frames())


def _open_video(path: Path, fps: float | None) -> MediaStream:
    capture = cv2.VideoCapture(str(path))
    if capture.isOpened():
        try:
            check_pixels(int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                         f"video {path}")
        except MediaError:
            capture.release()
            raise
    ok, bgr = capture.read() if capture.isOpened() else (False, None)
    if not ok or bgr is None:
        capture.release()
        raise MediaError(f"video {path} is unreadable (OpenCV decoded 0 frames); check the file "
                         "(ffprobe) or re-encode it, or quarantine the clip")
    native_fps = capture.get(cv2.CAP_PROP_FPS)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    rate = fps if fps is not None else native_fps
    if not (rate and np.isfinite(rate) and rate > 0):
        capture.release()
        raise MediaError(f"video {path} reports no frame rate; pass fps=")
    height, width = bgr.shape[:2]

    def frames() -> Generator[np.ndarray, None, None]:
        try:
            yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            while True:
                ok, frame = capture.read()
                if not ok:
                    return
                yield cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        finally:
            capture.release()

    return MediaStream(MediaInfo(path, "video", float(rate), width, height, count if count > 0 else None), frames())


def open_media(path: str | Path, fps: float | None = None) -> MediaStream:
    """Open a video file or a frame folder for streaming.

    Parameters
    ----------
    path : a video file (anything OpenCV's FFmpeg backend decodes) or a folder of frame images
    fps : frame rate; overrides the video's own, required for frame folders

    Raises
    ------
    MediaError
        The path does not exist, a folder has no images or no ``fps``, a video decodes no frame, or the
        first image is unreadable.
    """
    path = Path(path)
    if not path.exists():
        raise MediaError(f"media {path} does not exist; check the corpus' media root")
    return _open_folder(path, fps) if path.is_dir() else _open_video(path, fps)


def iter_frames(path: str | Path, fps: float | None = None) -> Iterator[np.ndarray]:
    """The frames of a clip, (H, W, 3) uint8 RGB, one at a time."""
    yield from open_media(path, fps).frames
