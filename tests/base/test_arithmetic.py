"""``M3T_REPRODUCIBLE=1`` (m3t.arithmetic): the settings it pins, the restart that applies them, and the bytes it
promises: the tiny pipeline's fit and tokenizer stages write the same floats whatever the CPU capability level,
thread counts and worker processes the environment asks for."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from m3t import arithmetic

ROOT = Path(__file__).resolve().parents[2]
# what a faster machine, or a user, would otherwise have choose the arithmetic
HOST = {"ATEN_CPU_CAPABILITY": "avx2", "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2", "MKL_CBWR": "AUTO",
        "NUMBA_CPU_NAME": "host", "ONEDNN_MAX_CPU_ISA": "AVX2", "OPENBLAS_CORETYPE": "Haswell"}


def clean_environment(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in arithmetic.PINNED and not k.startswith("M3T_REPRODUCIBLE")}
    return {**env, **extra}


def test_the_switch_reads_yes_and_no_and_names_anything_else():
    assert not arithmetic.enabled({}) and not arithmetic.enabled({"M3T_REPRODUCIBLE": "0"})
    assert arithmetic.enabled({"M3T_REPRODUCIBLE": "1"}) and arithmetic.enabled({"M3T_REPRODUCIBLE": " On "})
    with pytest.raises(ValueError, match="M3T_REPRODUCIBLE='maybe': use 1"):
        arithmetic.enabled({"M3T_REPRODUCIBLE": "maybe"})
    env = arithmetic.pinned_environment({"PATH": "/bin", "OMP_NUM_THREADS": "8"})
    assert env["PATH"] == "/bin" and env["OMP_NUM_THREADS"] == "1" and not arithmetic.missing(env)
    assert arithmetic.missing({"MKL_CBWR": "COMPATIBLE"}) == {k: v for k, v in arithmetic.PINNED.items()
                                                             if k != "MKL_CBWR"}
    assert "export M3T_REPRODUCIBLE=1" in arithmetic.describe()


def test_importing_m3t_restarts_the_process_into_the_pinned_arithmetic():
    # torch loads first, at the machine's settings; `import m3t` starts the command again with the pinned ones
    script = ("import torch, os\nimport m3t\nimport numpy\n"
              "from numpy._core._multiarray_umath import __cpu_features__ as f\n"
              "print(torch.backends.cpu.get_cpu_capability(), torch.get_num_threads(), torch.backends.mkldnn.enabled,"
              " os.environ['MKL_CBWR'], f.get('X86_V3'))")
    done = subprocess.run([sys.executable, "-c", script], env=clean_environment(M3T_REPRODUCIBLE="1", **HOST),
                          capture_output=True, text=True, timeout=300, check=True)
    assert done.stdout.split() == ["DEFAULT", "1", "False", "COMPATIBLE", "False"], done.stdout + done.stderr
    off = subprocess.run([sys.executable, "-c", script], env=clean_environment(**HOST), capture_output=True,
                         text=True, timeout=300, check=True)
    assert off.stdout.split()[1:4] == ["2", "True", "AUTO"]  # without the mode, nothing is touched


def run_tiny(out: Path, workers: int, env: dict[str, str]) -> dict[str, str]:
    done = subprocess.run([sys.executable, str(ROOT / "tests" / "reproducible_run.py"), str(out), str(workers)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_fit_and_tokenizers_write_the_same_bytes_whatever_threads_and_capability_the_machine_offers(tmp_path):
    import torch

    pinned = run_tiny(tmp_path / "a", 1, clean_environment(M3T_REPRODUCIBLE="1"))
    hostile = run_tiny(tmp_path / "b", 2, clean_environment(M3T_REPRODUCIBLE="1", **HOST))
    assert {"fit/train", "tokenizer/body", "tokenizer/hand", "tokenizer/face"} <= set(pinned)
    assert hostile == pinned  # 1 vs 2 worker processes, 1 vs 2 threads, default vs AVX2 kernels asked for
    if torch.backends.cpu.get_cpu_capability() == "DEFAULT":
        pytest.skip("this CPU offers torch no vector kernels: the control below would compare equal settings")
    # the control: the same run at the machine's own arithmetic writes other bytes, so the equality above is
    # the mode's doing (on this machine the fit and all three tokenizers differ)
    machine = run_tiny(tmp_path / "c", 2, clean_environment(**HOST))
    assert machine["tokenizer/body"] != pinned["tokenizer/body"]


GPU_TRAINING = """
import hashlib, sys
import m3t
import torch
from m3t.tokenizers.config import VAEConfig
from m3t.tokenizers.vae import MotionTokenizer
torch.manual_seed(0)
model = MotionTokenizer(VAEConfig(input_dim=24, levels=(5, 5, 4), quantizer=sys.argv[1], width=64, depth=2,
                                  vq_code_dim=8)).cuda()
optim = torch.optim.Adam(model.parameters(), lr=1e-3)
data = torch.randn(32, 64, 24, device="cuda")
for step in range(40):
    out = model(data[(step % 4) * 8:(step % 4 + 1) * 8])
    loss = (out.recon - data[(step % 4) * 8:(step % 4 + 1) * 8]).pow(2).mean() + out.quant_loss
    optim.zero_grad()
    loss.backward()
    optim.step()
h = hashlib.sha256()
for key, value in sorted(model.state_dict().items()):
    h.update(value.detach().cpu().numpy().tobytes())
print(h.hexdigest())
"""


@pytest.mark.skipif("not __import__('torch').cuda.is_available()", reason="needs a CUDA GPU")
@pytest.mark.parametrize("quantizer", ["fsq", "vq"])
def test_on_a_gpu_two_trainings_in_the_mode_write_the_same_weights(quantizer):
    """On an H200 (2026-11-28), 40 steps of this training without the mode gave other weights on every rerun
    (fsq, vq and vq_plain alike); with it, the same bytes."""
    def train(**extra: str) -> str:
        done = subprocess.run([sys.executable, "-c", GPU_TRAINING, quantizer], cwd=ROOT, capture_output=True,
                              text=True, timeout=600, env=clean_environment(**extra))
        assert done.returncode == 0, done.stderr[-3000:]
        return done.stdout.split()[-1]

    assert train(M3T_REPRODUCIBLE="1") == train(M3T_REPRODUCIBLE="1")
