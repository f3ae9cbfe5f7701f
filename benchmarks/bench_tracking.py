"""Tracking + fitting throughput on real data: decode vs MediaPipe inference vs fitting, in frames/s and shares.

No real sign-language video exists on this machine, so the two halves use the closest real material:
(a) decode + MediaPipe Holistic inference on a synthetic video made from a real photograph
    (scikit-image's ``astronaut``, translated across a wider canvas, mp4v), and
(b) fitting Anny to real MediaPipe-Holistic fingerspelling clips (``.pose`` files shipped in the
    ``spoken-to-signed`` wheel, one clip per language).
The per-frame costs of (a) and (b) are added to give the share of each step in a video -> fitted-params run.

    python benchmarks/bench_tracking.py [--frames 100] [--clips 4] [--iterations 250]
                                        [--out benchmarks/results/tracking.json]

Needs the tracking extra (``bash .ci/install-tracking``).
"""
from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "trackers"))  # test_tracking_real
sys.path.insert(0, str(Path(__file__).resolve().parent))

from m3t.body.factory import BodyConfig, load_body_model  # noqa: E402
from m3t.fitting.fit import FittingConfig, fit_track  # noqa: E402
from m3t.trackers.mediapipe_holistic import MediaPipeConfig, import_mediapipe, run_holistic  # noqa: E402
from m3t.trackers.posefile import load_pose_track  # noqa: E402
from m3t.trackers.track import landmark_slices  # noqa: E402
from report import write_and_log  # noqa: E402
from test_tracking_real import FIT, lexicon_clips, part_median_errors, translated_frames  # noqa: E402


def write_video(frames: list[np.ndarray], path: Path, fps: float = 25.0) -> Path:
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def bench_tracking(frames: int) -> dict:
    from skimage.data import astronaut

    image = astronaut()
    # Loop the translation so long videos stay inside the canvas: 25 positions, back and forth.
    positions = translated_frames(image, 25)
    sequence = [positions[i] for i in np.abs((np.arange(frames) + 24) % 48 - 24)]
    with tempfile.TemporaryDirectory() as tmp:
        video = write_video(sequence, Path(tmp) / "astronaut.mp4")
        start = time.perf_counter()
        out = run_holistic(video, MediaPipeConfig())
        wall = time.perf_counter() - start
    timing = out.timing.summary()
    conf = out.track.confidence
    parts = landmark_slices("mediapipe_holistic")
    return {
        "track_frames": int(timing["frames"]),
        "track_size": f"{out.track.image_size[0]}x{out.track.image_size[1]}",
        "decode_ms_per_frame": 1e3 * timing["decode_s"] / timing["frames"],
        "inference_ms_per_frame": 1e3 * timing["inference_s"] / timing["frames"],
        "tracking_frames_per_s": timing["frames_per_s"],
        "tracking_setup_s": wall - timing["decode_s"] - timing["inference_s"],  # graph construction etc.
        "pose_found_frac": float((conf[:, parts["pose"]].max(-1) > 0).mean()),
        "face_found_frac": float((conf[:, parts["face"]].max(-1) > 0).mean()),
    }


def bench_fitting(clips: int, iterations: int) -> dict:
    body = load_body_model(BodyConfig())
    correspondence = body.correspondence("mediapipe_holistic")
    parts = landmark_slices("mediapipe_holistic")
    chosen = {}
    for path in lexicon_clips():
        chosen.setdefault(path.parent.name, path)
    paths = [chosen[k] for k in sorted(chosen)][:: max(1, len(chosen) // clips)][:clips]
    cfg = dataclasses.replace(FIT, iterations=iterations)  # the configuration the tests bound
    fit_track(load_pose_track(paths[0]).track, body, FittingConfig(iterations=2, camera_iterations=2))  # warm-up
    frames = read_s = fit_s = 0.0
    part_errors: dict[str, list[float]] = {k: [] for k in parts}
    for path in paths:
        start = time.perf_counter()
        track = load_pose_track(path).track
        read_s += time.perf_counter() - start
        start = time.perf_counter()
        result = fit_track(track, body, cfg)
        fit_s += time.perf_counter() - start
        frames += track.num_frames
        for name, error in part_median_errors(body, result, track, correspondence).items():
            part_errors[name].append(error)
    return {
        "fit_clips": len(paths),
        "fit_languages": ",".join(p.parent.name for p in paths),
        "fit_frames": int(frames),
        "fit_iterations": iterations,
        "posefile_read_ms_per_frame": 1e3 * read_s / frames,
        "fitting_ms_per_frame": 1e3 * fit_s / frames,
        "fitting_frames_per_s": frames / fit_s,
        **{f"fit_median_reproj_px_{k}": float(np.mean(v)) for k, v in part_errors.items() if v},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="frames of the synthetic video")
    parser.add_argument("--clips", type=int, default=4, help="fingerspelling clips to fit")
    parser.add_argument("--iterations", type=int, default=FIT.iterations, help="fitting iterations per clip")
    parser.add_argument("--out", default="benchmarks/results/tracking.json")
    args = parser.parse_args()
    torch.manual_seed(0)
    mp = import_mediapipe()
    result = {"data": "tracking: synthetic mp4 of scikit-image's astronaut photograph (translated); fitting: real "
                      "MediaPipe-Holistic fingerspelling .pose clips from the spoken-to-signed wheel (no real sign "
                      "video on this machine)"}
    result.update(bench_tracking(args.frames))
    result.update(bench_fitting(args.clips, args.iterations))
    per_frame = {"decode": result["decode_ms_per_frame"], "inference": result["inference_ms_per_frame"],
                 "fitting": result["fitting_ms_per_frame"]}
    total = sum(per_frame.values())
    result.update({f"{k}_share": v / total for k, v in per_frame.items()})
    result["pipeline_frames_per_s"] = 1e3 / total
    result.update({"mediapipe": mp.__version__, "opencv": cv2.__version__, "torch": torch.__version__,
                   "torch_threads": torch.get_num_threads(), "machine": platform.machine()})
    write_and_log(result, args.out, "bench-tracking")


if __name__ == "__main__":
    main()
