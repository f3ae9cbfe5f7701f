"""What a file declares, checked before anything of that size is allocated (:mod:`m3t.declared`), on hand-made
streams and numbers at each bound: the caps and their environment keys, declared against stored bytes (plain and
compressed), and the bounded stream a pickle is read through (``read``, ``readline``, ``readinto``)."""
from __future__ import annotations

import io

import pytest

from m3t.declared import (
    MAX_BYTES,
    MAX_BYTES_ENV,
    MAX_RATIO_ENV,
    RATIO_FLOOR,
    BoundedReads,
    DeclaredSizeError,
    cap,
    check_bytes,
)


def test_a_cap_is_its_default_or_the_positive_number_its_key_sets(monkeypatch):
    monkeypatch.delenv(MAX_BYTES_ENV, raising=False)
    assert cap(MAX_BYTES_ENV, MAX_BYTES) == MAX_BYTES == 16 * 2**30
    monkeypatch.setenv(MAX_BYTES_ENV, " 1e3 ")
    assert cap(MAX_BYTES_ENV, MAX_BYTES) == 1000
    for bad in ("0", "-5", "lots"):
        monkeypatch.setenv(MAX_BYTES_ENV, bad)
        with pytest.raises(ValueError, match=rf"^{MAX_BYTES_ENV}='{bad}' is not a positive number; unset it"):
            cap(MAX_BYTES_ENV, MAX_BYTES)


def test_declared_bytes_are_checked_against_the_cap_and_what_the_file_stores(monkeypatch):
    monkeypatch.setenv(MAX_BYTES_ENV, "1000")
    check_bytes(1000, 1000, "f.npy", compressed=False)  # at the cap, stored whole: accepted
    with pytest.raises(DeclaredSizeError, match=r"^f.npy declares 1,001 bytes, more than the cap of 1,000; a "
                                                rf"legitimately huge file: raise {MAX_BYTES_ENV}$"):
        check_bytes(1001, 5000, "f.npy", compressed=False)
    with pytest.raises(DeclaredSizeError, match=r"^f.npy declares 11 bytes but holds 10 \(truncated or forged\)"):
        check_bytes(11, 10, "f.npy", compressed=False)
    monkeypatch.delenv(MAX_BYTES_ENV)
    monkeypatch.setenv(MAX_RATIO_ENV, "10")
    check_bytes(RATIO_FLOOR, 1, "z.npz:a", compressed=True)  # small members may compress as well as they like
    check_bytes(10 * 2**20, 2**20, "z.npz:a", compressed=True)  # exactly 10:1
    with pytest.raises(DeclaredSizeError, match=r"^z.npz:a declares 10,485,761 bytes from 1,048,576 compressed, "
                                                r"more than 10:1 \(a compression bomb\?\); .* raise M3T_MAX_INFLATE"):
        check_bytes(10 * 2**20 + 1, 2**20, "z.npz:a", compressed=True)


def test_the_bounded_stream_refuses_a_declared_length_the_file_cannot_hold():
    big = BoundedReads.SMALL + 1
    stream = BoundedReads(io.BytesIO(b"x" * 10 + b"line\n" + b"rest"), big + 100, "f.pkl", "its size")
    assert stream.read(4) == b"xxxx"
    buffer = bytearray(6)
    assert stream.readinto(buffer) == 6 and bytes(buffer) == b"xxxxxx"
    assert stream.readline() == b"line\n" and stream.read() == b"rest"
    # the budget went down by every byte given: 10 + 5 + 4 = 19 of big + 100
    with pytest.raises(DeclaredSizeError, match=rf"^f.pkl: a record declares {big + 82:,} bytes where at most "
                                                rf"{big + 81:,} can follow \(its size\)$"):
        stream.read(big + 82)
    with pytest.raises(DeclaredSizeError, match="a record declares"):
        stream.readinto(bytearray(big + 82))
    # a small read past the end just ends short, as at the end of any file
    small = BoundedReads(io.BytesIO(b"ab"), 2, "g.pkl", "its size")
    assert small.read(BoundedReads.SMALL) == b"ab" and small.read(1) == b""
    assert small.readinto(bytearray(4)) == 0
