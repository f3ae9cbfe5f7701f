"""The Anny model itself: built once per cache folder (~20 s the first time, writing a ~800 MB cache that later
loads read), then shared by every :class:`m3t.body.anny_body.AnnyBody` of the process, one copy per (device,
dtype). The build runs on one thread, so the cache holds the same bits whichever process built it.
"""
from __future__ import annotations

import copy
import os
import threading
from pathlib import Path

import torch

from m3t.arithmetic import cache_folder
from m3t.body.anny_targets import fast_target_reader

DEFAULT_CACHE_DIR = Path(".cache") / "anny"

_MODEL_LOCK = threading.Lock()
_MODELS: dict[object, object] = {}


def load_anny_model(cache_dir: Path, device: torch.device | None = None, dtype: torch.dtype = torch.float32):
    """Build (first time ~20 s, ~800 MB cache) or load the Anny model; one instance per process and
    (device, dtype), the others copied from the CPU float32 one. Callers never move a returned instance: it is
    shared by every :class:`m3t.body.anny_body.AnnyBody` of the process on that device."""
    key = str(Path(cache_folder(cache_dir)).resolve())  # built anew under M3T_REPRODUCIBLE: it holds computed floats
    device = torch.device(device or "cpu")
    with _MODEL_LOCK:
        if key not in _MODELS:
            import anny
            import anny.paths

            Path(key).mkdir(parents=True, exist_ok=True)
            anny.paths.set_anny_cache_path(key)
            os.environ.setdefault("ANNY_CACHE_DIR", key)
            # On one thread: Anny's first build (which writes the cache every later load reads) gives other
            # blendshape buffers on 2 threads than on 1 (entries up to 32 apart; three 1-thread builds, under
            # different hash seeds, were identical), and fits depended on which process built the cache (same
            # code and corpus: shard values up to 3e-3 apart).
            # Its text targets read in one pass each (m3t.body.anny_targets: the same tensors, ~8x faster).
            threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                with fast_target_reader():
                    # skinning "lbs": AnnyBody skins itself; Anny's default probes NVIDIA Warp for its
                    # skinning, which costs every process ~0.3 s of import and initialisation and a banner
                    model = anny.Anny(rig="anny", facial_actions="all", pose_parameterization="local-ref",
                                      skinning_method="lbs")
            finally:
                torch.set_num_threads(threads)
            _MODELS[key] = model.to(torch.float32)
        variant = (key, str(device), dtype)
        if (device.type, dtype) == ("cpu", torch.float32):
            return _MODELS[key]
        if variant not in _MODELS:
            _MODELS[variant] = copy.deepcopy(_MODELS[key]).to(device=device, dtype=dtype)
        return _MODELS[variant]
