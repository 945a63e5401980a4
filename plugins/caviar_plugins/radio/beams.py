"""DFT beam codebooks for planar arrays, and beam-pair gains.

For an N_y × N_z planar array the codebook is the Kronecker product of two DFT
codebooks, one per array axis: codeword (p, q) has the phase progression of the
p-th N_y-point DFT column along y and of the q-th N_z-point DFT column along z. An
8 × 8 array thus has 64 codewords that steer in two dimensions (the original CAVIAR
code used one 64-point DFT over the element index, which is not a grid of beams for
a planar array).

Element order follows the array's own element positions, so the codebook is right
whatever order the ray tracer lists the elements in.
"""

from __future__ import annotations

import numpy as np


def element_grid(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Integer grid indices (along y, along z) of each element of a planar array in
    the y-z plane, from element positions of shape (3, N) or (N, 3)."""
    pos = np.asarray(positions, dtype=float)
    if pos.shape[0] == 3 and pos.shape[1] != 3:
        pos = pos.T
    idx = []
    for axis in (1, 2):
        values = np.unique(np.round(pos[:, axis], 9))
        idx.append(np.searchsorted(values, np.round(pos[:, axis], 9)))
    n_y, n_z = idx[0].max() + 1, idx[1].max() + 1
    if n_y * n_z != len(pos):
        raise ValueError(f"elements do not form a full {n_y} x {n_z} grid in the y-z plane")
    return idx[0], idx[1], int(n_y), int(n_z)


def dft_codebook(positions: np.ndarray) -> np.ndarray:
    """Unit-norm codewords as the columns of an (N, N) complex matrix.

    Column ``p * N_z + q`` is the Kronecker-DFT codeword with index p along y and q
    along z: ``w[k] = exp(-2j·π·(p·m_y[k]/N_y + q·m_z[k]/N_z)) / sqrt(N)``.
    """
    m_y, m_z, n_y, n_z = element_grid(positions)
    p = np.repeat(np.arange(n_y), n_z)  # codeword's y index
    q = np.tile(np.arange(n_z), n_y)    # codeword's z index
    phase = np.outer(m_y, p) / n_y + np.outer(m_z, q) / n_z
    return np.exp(-2j * np.pi * phase) / np.sqrt(len(m_y))


def flat_dft_codebook(n: int) -> np.ndarray:
    """The 2023 CAVIAR code's codebook (``mimo_channels.dft_codebook``): an unnormalised
    n-point DFT over the flat element index, ``W[k, c] = exp(-2j·π·k·c / n)`` (|w|² = n).

    On an 8 × 8 planar array in Sionna's element order (k = row + 8·column) codeword c
    advances c/8 cycles per element along y and c/64 along z: 64 beams on a diagonal of
    the spatial-frequency torus, not a grid. Kept only for ``protocol = "paper"``.
    """
    k = np.arange(n)
    return np.exp(-2j * np.pi * np.outer(k, k) / n)


def beam_gains(h: np.ndarray, w_tx: np.ndarray, w_rx: np.ndarray) -> np.ndarray:
    """|w_rx^H · H · w_tx|² for every pair: H of shape (..., N_rx, N_tx) gives gains of
    shape (..., C_rx, C_tx) (receive codeword index first)."""
    return np.abs(np.conj(w_rx).T @ h @ w_tx) ** 2


def pair_index(rx_beam: int, tx_beam: int, n_tx_beams: int) -> int:
    """Flat beam-pair index: rx_beam · n_tx_beams + tx_beam (0 … 255 for 4 × 64)."""
    return rx_beam * n_tx_beams + tx_beam


def split_pair(index: int, n_tx_beams: int) -> tuple[int, int]:
    """(rx_beam, tx_beam) of a flat beam-pair index."""
    return divmod(int(index), n_tx_beams)
