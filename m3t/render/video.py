"""Video files of rendered frames: H.264 MP4 through the ffmpeg binary of the ``imageio-ffmpeg`` wheel (GIF
through Pillow when the target ends in ``.gif``), and the side-by-side layout every comparison video shares.

MP4s are what browsers, the MLflow UI and the dashboard play: H.264 (libx264), yuv420p (the 4:2:0 chroma that
every player decodes, which needs even frame sides: odd frames are padded by one edge row / column, never
resized), ``+faststart`` (the index at the front, so a browser starts playing before the whole file arrived).
Files are written to a temporary name beside the target and renamed (:func:`m3t.atomic.atomic_path`): a reader
never sees a half-encoded video, and a failure mid-stream leaves the previous file, or none.

Axis legend: H x W pixels, 3 RGB channels (uint8).
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np

from m3t.atomic import atomic_path

CRF = 20  # x264 constant rate factor: thin skeleton lines and mesh edges stay sharp; 23 is x264's default
LABEL_HEIGHT = 20  # pixels of the strip above each panel holding its label
FONT_SCALE = 0.45
BACKGROUND = 255  # white strips and gaps
SUBPIXEL = 4  # fractional bits of the fixed-point coordinates OpenCV draws lines and dots at (1/16 pixel)


def _ffmpeg():
    try:
        import imageio_ffmpeg
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError("writing MP4 videos needs the imageio-ffmpeg package (it ships an ffmpeg binary "
                                  "with libx264): pip install imageio-ffmpeg") from exc
    return imageio_ffmpeg


def _checked(frames: Iterable[np.ndarray]) -> tuple[np.ndarray, Iterator[np.ndarray]]:
    """The first frame and an iterator over all of them, each checked to be (H, W, 3) uint8 of the first's size."""
    iterator = iter(frames)
    first = next(iterator, None)
    if first is None:
        raise ValueError("no frame to write: a video needs at least one frame")

    def check(i: int, frame) -> np.ndarray:
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3 or 0 in frame.shape:
            raise ValueError(f"frame {i}: {frame.dtype} array of shape {frame.shape}, expected (H, W, 3) uint8")
        if i and frame.shape != shape:
            raise ValueError(f"frame {i}: shape {frame.shape}, but frame 0 was {shape}; every frame needs one size")
        return frame

    first = check(0, first)
    shape = first.shape

    def every() -> Iterator[np.ndarray]:
        yield first
        for i, frame in enumerate(iterator, 1):
            yield check(i, frame)

    return first, every()


def pad_even(frame: np.ndarray) -> np.ndarray:
    """(H, W, 3) -> (H + H % 2, W + W % 2, 3): the last row / column repeated where a side is odd (yuv420p
    halves the chroma resolution, so H.264 needs even sides)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_mp4(frames: Iterable[np.ndarray], path: str | Path, fps: float = 25.0, crf: int = CRF) -> Path:
    """Encode ``frames`` ((H, W, 3) uint8 RGB, all one size) as an H.264 MP4 at ``fps``; returns ``path``.

    Frames are streamed to ffmpeg as they come (a generator is never held in memory); the file appears
    (atomically) only once ffmpeg has finished it.
    """
    imageio_ffmpeg = _ffmpeg()
    if not fps > 0:
        raise ValueError(f"{path}: fps {fps!r}; expected a positive frame rate")
    first, frames = _checked(frames)
    height, width = pad_even(first).shape[:2]
    path = Path(path)
    with atomic_path(path, suffix=".mp4") as tmp:  # ffmpeg picks the container from the suffix
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (width, height), pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
            fps=Fraction(float(fps)).limit_denominator(1001), quality=None, codec="libx264", macro_block_size=1,
            ffmpeg_log_level="error", output_params=["-crf", str(int(crf)), "-movflags", "+faststart"])
        writer.send(None)  # start ffmpeg
        try:
            for frame in frames:
                writer.send(np.ascontiguousarray(pad_even(frame)))
        finally:
            writer.close()  # waits for ffmpeg to finish the file (or stops it on an error)
        with open(tmp, "rb") as fh:
            head = fh.read(12)
        if head[4:8] != b"ftyp":  # imageio-ffmpeg does not report ffmpeg's exit status
            raise RuntimeError(f"{path}: ffmpeg ({imageio_ffmpeg.get_ffmpeg_exe()}) wrote no MP4; see its messages "
                               "above (is libx264 in this ffmpeg build?)")
    return path


def write_gif(frames: Iterable[np.ndarray], path: str | Path, fps: float = 25.0) -> Path:
    """Write ``frames`` as a looping GIF (Pillow; every frame is held in memory: keep GIFs short)."""
    from PIL import Image

    _, frames = _checked(frames)
    images = [Image.fromarray(frame) for frame in frames]
    path = Path(path)
    with atomic_path(path, suffix=".gif") as tmp:
        images[0].save(tmp, save_all=True, append_images=images[1:], duration=max(20, round(1000 / fps)), loop=0)
    return path


def write_video(frames: Iterable[np.ndarray], path: str | Path, fps: float = 25.0) -> Path:
    """:func:`write_mp4` or, for a ``.gif`` target, :func:`write_gif`; any other suffix is refused."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mp4":
        return write_mp4(frames, path, fps)
    if suffix == ".gif":
        return write_gif(frames, path, fps)
    raise ValueError(f"{path}: videos are written as .mp4 (H.264) or .gif")


def _ascii(text: str) -> str:
    """OpenCV's Hershey fonts draw ASCII only; anything else becomes '?'."""
    return "".join(c if 32 <= ord(c) < 127 else "?" for c in str(text))


def text_strip(text: str, width: int, height: int = LABEL_HEIGHT,
               color: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """(height, width, 3) white strip with ``text`` centred, shrunk (then cut with '...') to fit."""
    import cv2

    strip = np.full((height, width, 3), BACKGROUND, dtype=np.uint8)
    text, scale, font = _ascii(text), FONT_SCALE, cv2.FONT_HERSHEY_SIMPLEX
    (w, h), _ = cv2.getTextSize(text, font, scale, 1)
    if w > width - 4:
        scale = max(0.3, scale * (width - 4) / w)
        while text and cv2.getTextSize(text, font, scale, 1)[0][0] > width - 4:
            text = text[:-4] + "..." if len(text) > 4 else ""
        (w, h), _ = cv2.getTextSize(text, font, scale, 1)
    cv2.putText(strip, text, ((width - w) // 2, (height + h) // 2), font, scale, color, 1, cv2.LINE_AA)
    return strip


def side_by_side(panels: Sequence[np.ndarray], labels: Sequence[str], title: str = "", gap: int = 4) -> np.ndarray:
    """Panels ((H_i, W_i, 3) uint8) in a row left to right, each under its label, with ``title`` above all.

    Shorter panels are padded at the bottom with white; ``gap`` white pixels separate the panels.
    """
    if not panels or len(panels) != len(labels):
        raise ValueError(f"side by side: {len(panels)} panels and {len(labels)} labels; expected as many, at least one")
    height = max(p.shape[0] for p in panels) + LABEL_HEIGHT
    columns = []
    for k, (panel, label) in enumerate(zip(panels, labels)):
        column = np.full((height, panel.shape[1], 3), BACKGROUND, dtype=np.uint8)
        column[:LABEL_HEIGHT] = text_strip(label, panel.shape[1])
        column[LABEL_HEIGHT:LABEL_HEIGHT + panel.shape[0]] = panel
        columns.append(column)
        if k + 1 < len(panels) and gap > 0:
            columns.append(np.full((height, gap, 3), BACKGROUND, dtype=np.uint8))
    row = np.concatenate(columns, axis=1)
    if title:
        row = np.concatenate([text_strip(title, row.shape[1]), row], axis=0)
    return row


def held(length: int, t: int) -> int:
    """The frame a sequence of ``length`` frames shows at time ``t``: its last once it has ended."""
    return min(t, length - 1)


def progress_label(label: str, length: int, t: int) -> str:
    """``label``, or ``label (n/n)`` once its sequence of ``length`` frames has ended and holds its last frame."""
    return f"{label} ({length}/{length})" if t >= length else label
