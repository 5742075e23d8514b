"""Codebook indices packed several to an int64, the form a latent dataset stores them in.

LeRobot's data loader turns every column of a row into a Python list and then a tensor,
one row at a time, so its cost grows with the numbers in a row: 144 int16 indices per
image made the code columns 70 % of a row's read (BENCHMARKS.md). A 512-entry codebook
needs 9 bits an index, so an int64 holds 7 of them (63 bits; the sign bit stays clear):
144 indices become 21 numbers and a row reads about twice as fast. Index i of an image
sits in number i // per, bits (i % per) * bits and up.
"""

from __future__ import annotations

import numpy as np


def code_bits(codebook_size: int) -> int:
    """Bits an index of a codebook of this size needs."""
    if codebook_size < 2:
        raise ValueError(f"a codebook needs at least 2 codes, got {codebook_size}")
    return (codebook_size - 1).bit_length()


def codes_per_number(codebook_size: int) -> int:
    return 63 // code_bits(codebook_size)


def packed_length(codes: int, codebook_size: int) -> int:
    """Numbers a row of `codes` indices packs into."""
    return -(-codes // codes_per_number(codebook_size))


def pack_codes(indices: np.ndarray, codebook_size: int) -> np.ndarray:
    """(N, codes) indices in [0, codebook_size) -> (N, packed_length) int64."""
    indices = np.asarray(indices).reshape(len(indices), -1).astype(np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= codebook_size):
        raise ValueError(f"codebook indices must lie in [0, {codebook_size})")
    bits, per = code_bits(codebook_size), codes_per_number(codebook_size)
    padded = np.zeros((len(indices), packed_length(indices.shape[1], codebook_size) * per), np.int64)
    padded[:, : indices.shape[1]] = indices
    shifts = bits * np.arange(per, dtype=np.int64)
    return (padded.reshape(len(indices), -1, per) << shifts).sum(axis=-1)


def unpack_codes(packed: np.ndarray, codebook_size: int, codes: int) -> np.ndarray:
    """(N, packed_length) int64 -> (N, codes) uint16, the inverse of `pack_codes`."""
    packed = np.asarray(packed, np.int64).reshape(len(packed), -1)
    bits, per = code_bits(codebook_size), codes_per_number(codebook_size)
    shifts = bits * np.arange(per, dtype=np.int64)
    unpacked = (packed[:, :, None] >> shifts) & ((1 << bits) - 1)
    return unpacked.reshape(len(packed), -1)[:, :codes].astype(np.uint16)
