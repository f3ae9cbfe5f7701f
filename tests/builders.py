"""Shared builders of the test suite: motions, a camera, the tiny preset's params, tiny tokenizers and their configs.

Imported by test modules of several components (``from builders import smooth_motion``); the fixtures that several
components share are in ``conftest.py``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import roma
import torch

from m3t.body.protocol import Modality, ModalityLayout
from m3t.body.rotations import matrix_to_6d, sixd_to_matrix
from m3t.camera import Camera, look_at
from m3t.config import load_params
from m3t.tokenizers.config import TokenizerConfig, VAEConfig
from m3t.tokenizers.vae import MotionTokenizer

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------------ body motions
def smooth_motion(body, frames=16, seed=0, amplitude=0.25):
    """Rest pose plus slow sinusoidal rotations (``amplitude`` rad scale) of every driven joint and a moving face."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, frames)[:, None, None]
    params = body.rest_params(frames)
    for m in body.layout.modalities:
        if m.kind == "rotation6d":
            n = len(m.labels)
            amp, phase = amplitude * torch.randn(1, n, 3, generator=g), 6 * torch.rand(1, n, 1, generator=g)
            rest = sixd_to_matrix(params[m.name].reshape(frames, n, 6))
            params[m.name] = matrix_to_6d(roma.rotvec_to_rotmat(amp * torch.sin(3 * t + phase)) @ rest).reshape(frames, -1)
        else:
            params[m.name] = (0.3 + 0.25 * torch.sin(4 * t[..., 0] + 6 * torch.rand(1, m.dim, generator=g))).clamp(0, 1)
    return params


def random_params(body, batch, scale=0.4, seed=0):
    g = torch.Generator().manual_seed(seed)
    params = body.rest_params(batch)
    for m in body.layout.modalities:
        if m.kind == "rotation6d":
            rotvec = scale * torch.randn(batch, len(m.labels), 3, generator=g)
            params[m.name] = matrix_to_6d(roma.rotvec_to_rotmat(rotvec)).reshape(batch, -1)
        else:
            params[m.name] = torch.rand(batch, m.dim, generator=g)
    return params


def jittered_motion(body, frames: int = 3, seed: int = 0) -> dict[str, np.ndarray]:
    """Rest pose plus small random rotations / facial actions (within bounds), ``frames`` frames."""
    rng = np.random.default_rng(seed)
    rest = {k: v.numpy().astype(np.float64) for k, v in body.rest_params(frames).items()}
    out = {}
    for m in body.layout.modalities:
        noise = rng.normal(0.0, 0.05, rest[m.name].shape)
        value = rest[m.name] + (np.abs(noise) if m.kind == "scalar" else noise)
        out[m.name] = np.clip(value, *m.bounds) if m.bounds is not None else value
    return out


# ------------------------------------------------------------------------------------------------ camera
def front_camera():
    eye = np.array([0.15, -2.4, 0.45])
    rot = look_at(eye, np.array([0.0, 0.0, 0.4]), np.array([0.0, 0.0, 1.0]))
    return Camera(700.0, 700.0, 256.0, 256.0, tuple(map(tuple, rot)), tuple((-rot @ eye).tolist()), 512, 512)


# ------------------------------------------------------------------------------------------------ tiny preset
def tiny_params(tmp_path: Path, **fit_corpus):
    """The tiny preset with the synthetic corpus at tmp/corpus and its shards at tmp/shards/synthetic."""
    params = load_params(ROOT / "params.yaml", preset="tiny", overrides={
        "data": {"shards_root": str(tmp_path / "shards")},
        "corpora": {"synthetic": {"root": str(tmp_path / "corpus")}},
        "fit_corpus": {"cache_dir": str(tmp_path / "cache"), **fit_corpus}})
    return params


# Clips per split of the tiny fitted shards (the ``shards_dir`` fixture of conftest.py) and the tiny tokenizer.
SPLITS = {"train": 4, "dev": 1, "test": 1}
TINY_MODEL = TokenizerConfig(width=32, depth=2)


# ------------------------------------------------------------------------------------------------ tiny tokenizers
# A small hand-made layout of the four motion streams (no body model needed to tokenise) and untrained tokenizers
# of its three groups; the tokenizer-training tests' model and config.
TINY_TOKENIZER = TokenizerConfig(width=8, depth=2, dilation_growth=3)
LAYOUT = ModalityLayout(
    (Modality("body", "rotation6d", ("spine", "neck")),
     Modality("left_hand", "rotation6d", ("wrist.L",), mirror_of="right_hand"),
     Modality("right_hand", "rotation6d", ("wrist.R",), mirror_of="left_hand"),
     Modality("face", "scalar", ("jaw", "smile", "blink"), bounds=(0.0, 1.0))),
    ("height", "weight"))
DIMS = {"body": LAYOUT.dims["body"], "hand": LAYOUT.dims["right_hand"], "face": LAYOUT.dims["face"]}
NO_FACE = ModalityLayout(LAYOUT.modalities[:3], LAYOUT.identity_labels)
"""A layout without the face stream: a shard fitted with another body model."""
TINY_VAE = VAEConfig(input_dim=3, levels=(5, 5, 4), width=8, depth=1)  # the tokenizer-training tests' model


def tiny_train_cfg(cache_dir, epochs: int, batch_size: int, windows_per_clip: int = 1, **extra):
    """The tokenizer-training tests' config: 8-frame windows, one warm-up epoch, on the CPU unless ``extra``
    names a device."""
    from m3t.tokenizers.config import TokenizerTrainConfig

    return TokenizerTrainConfig(cache_dir=str(cache_dir), epochs=epochs, warmup_epochs=1, batch_size=batch_size,
                                window=8, windows_per_clip=windows_per_clip, **{"device": "cpu", **extra})


def tiny_tokenizers(dims: dict[str, int] = DIMS, seed: int = 0) -> dict[str, MotionTokenizer]:
    """Untrained tokenizers of the three groups, with non-trivial normalisation statistics."""
    torch.manual_seed(seed)
    models = {}
    for group, dim in dims.items():
        model = MotionTokenizer(TINY_TOKENIZER.vae_config(group, dim)).eval()
        model.set_normalisation(0.1 * torch.randn(dim), 0.5 + torch.rand(dim))
        models[group] = model
    return models


class RecordingRun:
    """A stand-in MLflow run (:func:`m3t.experiment.start_run`'s): records what a stage driver logs, artifacts as
    ``(path, folder)``."""

    def __init__(self):
        self.params, self.metrics, self.artifacts = {}, [], []

    def log_params(self, params):
        self.params.update(params)

    def log_metrics(self, metrics, step=None):
        self.metrics.append((dict(metrics), step))

    def log_artifact(self, path, folder=None):
        self.artifacts.append((Path(path), folder))
