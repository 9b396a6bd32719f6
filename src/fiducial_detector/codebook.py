"""The armourcam codebook: 66 cyclic 16-bit codes, minimum Hamming distance 4 over all rotations.

Bit layout
----------
The coding track is divided into ``BITS = 16`` equal sectors. Sector ``k`` spans the polar angles
``[2*pi*k/16, 2*pi*(k+1)/16)`` of the *target frame* (x to the right on the printed sheet, y up on
the sheet, angles counter-clockwise, i.e. as seen when looking at the printed face). Bit ``k`` of a
code word is 1 where sector ``k`` is printed black.

Why this codebook
-----------------
A fiducial glued to an armour unit can be seen at any in-plane rotation, so a code is the whole
class of its 16 cyclic rotations. Codes are chosen greedily in increasing numeric order among words
that

* have 5 to 11 black sectors and at least 4 black/white transitions, so the track is neither a
  plain ring nor a plain disc and its contrast can always be measured from the track itself;
* differ from each of their own non-trivial rotations in at least 4 bits, so no code is
  rotationally symmetric and the in-plane orientation is unique;
* differ from every rotation of every earlier code in at least 4 bits.

Distance 4 lets the reader correct any single wrong sector and *detect* any two wrong sectors, so a
two-sector misread is rejected instead of becoming a wrong code. The greedy construction is
deterministic; the table is computed once at import (about 0.1 s) and the properties are asserted by
``tests/fiducial_detector/test_codebook.py``. 16 bits is the smallest track giving at least 64 codes
at distance 4 (14 bits gives fewer than 40).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

BITS = 16
MIN_DISTANCE = 4
_MASK = (1 << BITS) - 1


def rotate(word: int, k: int) -> int:
    """Rotate a ``BITS``-bit word so that sector ``k`` becomes sector 0."""
    k %= BITS
    return ((word >> k) | (word << (BITS - k))) & _MASK


def popcount(word: int) -> int:
    """Number of black sectors of a word."""
    return bin(word).count("1")


@lru_cache(maxsize=1)
def codewords() -> tuple[int, ...]:
    """All code words, indexed by code number (``codewords()[code]`` is the word at rotation 0)."""
    pop = np.array([popcount(i) for i in range(1 << BITS)], dtype=np.int8)
    forbidden = np.zeros(1 << BITS, dtype=bool)
    # Every word within Hamming distance MIN_DISTANCE - 1 of a chosen rotation is excluded.
    singles = [1 << i for i in range(BITS)]
    ball = [0, *singles]
    ball += [a | b for i, a in enumerate(singles) for b in singles[i + 1 :]]
    ball += [
        a | b | c
        for i, a in enumerate(singles)
        for j, b in enumerate(singles[i + 1 :], start=i + 1)
        for c in singles[j + 1 :]
    ]
    ball_arr = np.array(ball, dtype=np.int64)
    chosen: list[int] = []
    for word in range(1 << BITS):
        if forbidden[word] or not 5 <= pop[word] <= 11:
            continue
        transitions = pop[word ^ rotate(word, 1)]
        if transitions < 4:
            continue
        rotations = [rotate(word, k) for k in range(BITS)]
        if min(int(pop[word ^ r]) for r in rotations[1:]) < MIN_DISTANCE:
            continue
        chosen.append(word)
        for r in rotations:
            forbidden[np.bitwise_xor(ball_arr, r)] = True
    return tuple(chosen)


def code_count() -> int:
    """Number of codes in the codebook."""
    return len(codewords())


def code_bits(code: int) -> NDArray[np.uint8]:
    """The 16 sector bits of ``code`` at rotation 0, sector 0 first (1 = black).

    Raises
    ------
    ValueError
        If ``code`` is not in ``range(code_count())``.
    """
    words = codewords()
    if not 0 <= code < len(words):
        raise ValueError(f"code {code} is not in the codebook (0..{len(words) - 1})")
    word = words[code]
    return np.array([(word >> k) & 1 for k in range(BITS)], dtype=np.uint8)


@lru_cache(maxsize=1)
def rotation_table() -> NDArray[np.uint8]:
    """All rotations of all codes as bits: shape ``(n_codes, BITS, BITS)``, ``[c, k]`` = code c
    rotated so that its sector ``k`` is read first."""
    words = codewords()
    table = np.zeros((len(words), BITS, BITS), dtype=np.uint8)
    for c, word in enumerate(words):
        for k in range(BITS):
            r = rotate(word, k)
            table[c, k] = [(r >> i) & 1 for i in range(BITS)]
    return table


def decode(bits: NDArray[np.uint8] | NDArray[np.bool_]) -> tuple[int, int, int]:
    """Best code for 16 bits read from sector 0 onwards.

    Parameters
    ----------
    bits : (16,) array of {0, 1}
        Sector values read counter-clockwise in the target frame, starting at some unknown sector.

    Returns
    -------
    code, rotation, distance : int
        The nearest code, the sector of the code that was read first, and the Hamming distance.
        Ties are impossible below distance 2 (the codebook's minimum distance is 4).
    """
    b = np.asarray(bits, dtype=np.uint8).reshape(1, 1, BITS)
    dist = np.count_nonzero(rotation_table() != b, axis=2)
    flat = int(np.argmin(dist))
    code, rot = divmod(flat, BITS)
    return code, rot, int(dist[code, rot])
