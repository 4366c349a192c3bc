"""Scrambled Sobol points without importing ``scipy.stats`` (0.5-1 s of start-up).

The sequence is the one ``scipy.stats.qmc.Sobol(d, scramble=True, rng=generator)`` draws
(30 bits, Joe and Kuo's direction numbers, linear matrix scrambling plus a digital shift, the
points in Gray-code order), so plans stay what they were; tests compare the two.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

BITS = 30

# Joe & Kuo (2008), new-joe-kuo-6.21201: per dimension the primitive polynomial (with its
# leading and trailing 1) and the initial direction numbers m_1..m_s. Dimension 1 is the
# van der Corput sequence.
_POLY = (1, 3, 7, 11, 13, 19, 25, 37, 41, 47, 55, 59)
_VINIT = ((1,), (1,), (1, 3), (1, 3, 1), (1, 1, 1), (1, 1, 3, 3), (1, 3, 5, 13),
          (1, 1, 5, 5, 17), (1, 1, 5, 5, 5), (1, 1, 7, 11, 19), (1, 1, 5, 1, 1),
          (1, 1, 1, 3, 11))
MAX_DIM = len(_POLY)


def _direction_numbers(d: int) -> NDArray[np.uint64]:
    """Direction numbers (d, BITS), column j scaled by 2**(BITS-1-j)."""
    v = np.zeros((d, BITS), dtype=np.uint64)
    v[0, :] = 1
    for k in range(1, d):
        p = _POLY[k]
        s = p.bit_length() - 1
        row = [int(x) for x in _VINIT[k][:s]]
        for j in range(s, BITS):
            new = row[j - s]
            for i in range(s):
                if (p >> (s - 1 - i)) & 1:
                    new ^= row[j - i - 1] << (i + 1)
            row.append(new)
        v[k, :] = row
    return v << np.arange(BITS - 1, -1, -1, dtype=np.uint64)


def _bits_msb_first(x: NDArray[np.uint64]) -> NDArray[np.uint8]:
    """(..., BITS) binary digits of ``x`` (...), the most significant first."""
    shifts = np.arange(BITS - 1, -1, -1, dtype=np.uint64)
    return ((x[..., None] >> shifts) & np.uint64(1)).astype(np.uint8)


class Sobol:
    """Scrambled Sobol sequence in [0, 1)^d, drawn in order by :meth:`random`.

    Parameters
    ----------
    d
        Dimension, 1..MAX_DIM.
    rng
        Generator of the scrambling; a child is spawned from it, as scipy does.
    """

    def __init__(self, d: int, rng: np.random.Generator) -> None:
        if not 1 <= d <= MAX_DIM:
            raise ValueError(f"Sobol points of dimension 1..{MAX_DIM}, not {d}")
        bg = rng.bit_generator
        gen = np.random.Generator(type(bg)(bg.seed_seq.spawn(1)[0]))  # type: ignore[attr-defined]
        weights = np.uint64(1) << np.arange(BITS, dtype=np.uint64)
        shift_bits = gen.integers(2, size=(d, BITS), dtype=np.uint32)
        self._shift = (shift_bits.astype(np.uint64) * weights).sum(axis=1)
        ltm = np.tril(gen.integers(2, size=(d, BITS, BITS), dtype=np.uint32))
        ltm[:, np.arange(BITS), np.arange(BITS)] = 1
        # linear matrix scrambling: bit BITS-1-p of a scrambled direction number is the
        # parity of row p of the lower-triangular matrix and the number's bits, both most
        # significant first
        v_bits = _bits_msb_first(_direction_numbers(d))               # (d, BITS, BITS)
        par = np.einsum("dpk,djk->djp", ltm.astype(np.int64), v_bits.astype(np.int64)) & 1
        self._v = (par.astype(np.uint64) << np.arange(BITS - 1, -1, -1, dtype=np.uint64)
                   ).sum(axis=2).astype(np.uint64)
        self.d = d
        self.num_generated = 0
        # per byte of the Gray code, the XOR of the direction numbers of every bit pattern
        self._tables: list[NDArray[np.uint64]] = []
        for k in range(0, BITS, 8):
            t = np.zeros((256, d), dtype=np.uint64)
            for b in range(min(8, BITS - k)):
                t[1 << b:2 << b] = t[:1 << b] ^ self._v[:, k + b]
            self._tables.append(t)

    def random(self, n: int) -> NDArray[np.float64]:
        """The next ``n`` points, shape (n, d)."""
        i = np.arange(self.num_generated, self.num_generated + n, dtype=np.int64)
        gray = i ^ (i >> 1)
        x = np.broadcast_to(self._shift, (n, self.d)).copy()
        for k, table in enumerate(self._tables):         # XOR of the direction numbers of
            x ^= table[(gray >> (8 * k)) & 255]          # the set bits, a byte at a time
        self.num_generated += n
        return x * (1.0 / 2**BITS)

    def random_base2(self, m: int) -> NDArray[np.float64]:
        """The next 2**m points, shape (2**m, d)."""
        return self.random(2**m)
