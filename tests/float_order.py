"""Comparing the numbers of one computation made in two processes or at two thread counts: a training in worker
processes against the same training in this process, a fit on Dask workers against the fit here.

Such numbers are equal up to float rounding, not bit for bit, on every x86 CPU. Float addition is not associative,
and what orders a sum differs between the two runs:

- the thread count splits a reduction (a matmul's inner dimension, a convolution, a sum over a batch) into other
  partial sums; the stages' main process has two threads and computes shared inputs (the probe's frozen encoder
  features, the skeletons) before its one-thread workers train on them;
- MKL and oneDNN pick their kernels by the CPU's vector width (AVX2 or AVX-512) and, outside MKL's strict
  reproducibility mode, by the operands' memory alignment, which another process's heap decides.

Each reordered float32 reduction moves its result by about one unit in the last place (2**-24 = 6e-8 relative), and
a training carries the difference into every later step. Measured on an AMD EPYC (AVX2, no AVX-512) with the four
worker tests of this suite (tokenizers, SGSA / PT, the probe, the judges: 2-8 epochs each): reported losses and
metrics moved by at most 1e-7 relative (the probe's loss in the 7th digit, 1.2356710 against 1.2356709), weights by
at most 1.7e-6 of the tensor's largest entry, except the attention key biases (:func:`key_bias_rows`). The
tolerances below (1e-4) leave a margin of ~60x and more over that and stay far below what a real mistake moves:
another seed, another job's data, a skipped or repeated epoch change losses and weights in the 2nd-3rd digit. Where
an integer is derived from such floats (a token chosen by its nearest code), :func:`assert_close_counts` allows the
few flips of near-ties that a rounding difference can cause.

Bits are compared only where nothing reorders a float sum: integers, copies, text; and one computation repeated on
the same host at the same thread count in every process involved (a fit on one-thread Dask workers against the
same fit on one thread here, a killed and resumed stage against an uninterrupted one). There the kernels (chosen
by this CPU's features) and the reductions' partition (chosen by the thread count) are the same; what a process
could still change, the operands' memory alignment, is taken out by MKL's strict reproducibility mode
(``MKL_CBWR=AUTO,STRICT``, set by conftest.py; MKL honours it on CPUs with AVX2) and torch aligns its own
allocations to 64 bytes. Held on an Intel AVX-512 machine and on an AMD EPYC AVX2 one.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

RTOL = 1e-4  # relative, for reported numbers (losses, metrics): measured drift <= 2e-6
WEIGHT_TOL = 1e-4  # for weights, relative to the largest magnitude of the tensor: measured drift <= 4e-6


def assert_close_numbers(a, b, what: str = "value", rtol: float = RTOL) -> None:
    """``a`` and ``b`` (numbers, or dicts / lists / tuples of them, as JSON reports and epoch records are) equal in
    structure, keys, strings and integers, and in floats up to ``rtol`` (``1e-9`` absolute near zero); the message
    names the first differing key."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert a.keys() == b.keys(), f"{what}: keys {sorted(a.keys() ^ b.keys())} only on one side"
        for key in a:
            assert_close_numbers(a[key], b[key], f"{what}[{key!r}]", rtol)
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        assert len(a) == len(b), f"{what}: {len(a)} against {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_close_numbers(x, y, f"{what}[{i}]", rtol)
    elif isinstance(a, float) or isinstance(b, float):
        assert isinstance(a, (int, float)) and isinstance(b, (int, float)), f"{what}: {a!r} against {b!r}"
        if math.isnan(a) or math.isnan(b):
            assert math.isnan(a) and math.isnan(b), f"{what}: {a!r} against {b!r}"
        else:
            assert math.isclose(a, b, rel_tol=rtol, abs_tol=1e-9), f"{what}: {a!r} against {b!r} (rtol {rtol})"
    else:
        assert a == b, f"{what}: {a!r} against {b!r}"


def assert_close_json(one: Path, two: Path, rtol: float = RTOL) -> None:
    """Two JSON (or JSON-lines) files with the same content up to float rounding (:func:`assert_close_numbers`)."""
    def read(path: Path):
        text = path.read_text()
        if path.suffix == ".jsonl":
            return [json.loads(line) for line in text.splitlines() if line.strip()]
        return json.loads(text)

    assert_close_numbers(read(one), read(two), one.name, rtol)


def key_bias_rows(name: str, tensor: torch.Tensor) -> slice | None:
    """The rows of parameter ``name`` that are an attention key projection's bias, or None. Softmax is invariant to a
    shift shared by all keys, so these get a zero gradient in exact arithmetic and move only by rounding noise, which
    Adam normalises into steps of the learning rate's size: their values are noise (two runs differ by up to ~lr x
    steps) and change no output. torch's ``in_proj_bias`` stacks the query, key and value biases (the middle third);
    this project's attention modules name theirs ``k.bias``."""
    if name.endswith("in_proj_bias"):
        third = tensor.shape[0] // 3
        return slice(third, 2 * third)
    if name.endswith(".k.bias"):
        return slice(None)
    return None


def assert_close_weights(one: Path, two: Path, name: str, tol: float = WEIGHT_TOL) -> None:
    """Checkpoint ``name`` in folders ``one`` and ``two`` holds the same tensors (names, shapes, dtypes) with values
    equal up to ``tol`` x the tensor's largest magnitude (integer tensors exactly); attention key biases
    (:func:`key_bias_rows`) are compared in shape only."""
    a, b = (torch.load(folder / name, weights_only=False)["state_dict"] for folder in (one, two))
    assert a.keys() == b.keys(), f"{name}: tensors {sorted(a.keys() ^ b.keys())} only on one side"
    for key in a:
        x, y = a[key], b[key]
        assert x.shape == y.shape and x.dtype == y.dtype, f"{name} {key}: {x.shape} {x.dtype} against {y.shape} {y.dtype}"
        if not x.is_floating_point():
            assert torch.equal(x, y), f"{name} {key}"
            continue
        rows = key_bias_rows(key, x)
        if rows is not None:
            keep = torch.ones(x.shape[0], dtype=torch.bool)
            keep[rows] = False
            x, y = x[keep], y[keep]
        scale = float(x.abs().max()) if x.numel() else 0.0
        torch.testing.assert_close(y, x, rtol=0, atol=tol * max(scale, 1e-6), msg=lambda m: f"{name} {key}: {m}")


def assert_close_counts(a: dict | list, b: dict | list, what: str, flips: float = 0.02) -> None:
    """Histograms (nested dicts / lists of integer counts, or other values compared exactly) equal in structure and
    totals, with at most ``flips`` of the total moved from one bin to another: a code or class chosen as the nearest
    of two near-tied candidates can go either way under a rounding difference."""
    def leaves(x, path=""):
        if isinstance(x, dict):
            for k in sorted(x):
                yield from leaves(x[k], f"{path}/{k}")
        elif isinstance(x, (list, tuple)):
            for i, v in enumerate(x):
                yield from leaves(v, f"{path}/{i}")
        else:
            yield path, x

    left, right = dict(leaves(a)), dict(leaves(b))
    assert left.keys() == right.keys(), f"{what}: entries {sorted(left.keys() ^ right.keys())} only on one side"
    counts = [k for k, v in left.items() if isinstance(v, int) and not isinstance(v, bool)]
    for k in left.keys() - set(counts):
        assert_close_numbers(left[k], right[k], f"{what}{k}")
    total = sum(left[k] for k in counts)
    assert total == sum(right[k] for k in counts), f"{what}: totals {total} against {sum(right[k] for k in counts)}"
    moved = sum(abs(left[k] - right[k]) for k in counts) / 2
    assert moved <= flips * max(total, 1), f"{what}: {moved} of {total} counts moved between bins"

