"""Morton codes (Z-order) of 3D points and the bit helpers the BVH builders split with."""

from __future__ import annotations

import numpy as np


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """Insert two zero bits between each of the low 21 bits of x (uint64)."""
    x = x & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x



def morton_codes(points: np.ndarray, bits: int = 17) -> np.ndarray:
    """51-bit Morton codes (uint64) of points (P,3), quantised to `bits` bits per axis in their bounds."""
    lo = points.min(axis=0)
    ext = points.max(axis=0) - lo
    scale = np.where(ext > 0, ((1 << bits) - 1) / np.where(ext > 0, ext, 1.0), 0.0)
    q = np.clip(((points - lo) * scale).astype(np.int64), 0, (1 << bits) - 1).astype(np.uint64)
    return (_spread_bits(q[:, 0]) << np.uint64(2)) | (_spread_bits(q[:, 1]) << np.uint64(1)) | _spread_bits(q[:, 2])



def highest_bit(x: np.ndarray) -> np.ndarray:
    """Index of the highest set bit of nonzero uint64 values below 2**53 (exact in float64)."""
    return (np.frexp(x.astype(np.float64))[1] - 1).astype(np.uint64)
