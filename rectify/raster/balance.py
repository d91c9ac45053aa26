"""Radiometric balancing of overlapping orthophotos: a gain and an offset per image and band.

Every image i and band b gets ``v' = g_ib v + o_ib``. From the values of two images i, j at the same
ground points of their overlap (samples of the mosaic's grid), the corrections are the least-squares
solution of ``g_ib v_i + o_ib - g_jb v_j - o_jb = 0`` over all sample points of all overlapping pairs, with
one of two datum constraints that the differences alone leave free:

* ``reference``: image ``ref`` keeps its values (g = 1, o = 0);
* ``mean``: the mean gain is 1 and the mean offset 0 over the images (no image is privileged; the
  mosaic's overall level stays that of the average image).

Solved per band as the bordered normal equations ``[[N, A^T], [A, 0]] [x; l] = [0; b]`` (N from the
sample sums, A the constraints). Every image must overlap another, and the overlap graph must be
connected (else a group of images would float freely): checked, with the image named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError

__all__ = ["Balance", "PairStats", "estimate_balance"]

#: common samples of a pair below which the pair is not counted as an overlap
MIN_COMMON = 16


@dataclass(frozen=True)
class PairStats:
    """An overlapping pair (0-based image indices), its common samples and the RMS difference per band
    before and after the correction (image units)."""

    i: int
    j: int
    samples: int
    rms_before: tuple[float, ...]
    rms_after: tuple[float, ...]


@dataclass(frozen=True, eq=False)
class Balance:
    """Gains and offsets (n, bands) and the overlaps' statistics; ``mode`` ``mean`` or ``reference``."""

    gains: NDArray[np.float64]
    offsets: NDArray[np.float64]
    pairs: tuple[PairStats, ...]
    mode: str
    reference: int | None = None

    @classmethod
    def identity(cls, n: int, bands: int) -> Balance:
        return cls(np.ones((n, bands)), np.zeros((n, bands)), (), "none")

    def apply(self, i: int, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Image i's values (..., bands) corrected."""
        return values * self.gains[i] + self.offsets[i]


def _components(n: int, edges: list[tuple[int, int]]) -> list[int]:
    parent = list(range(n))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        parent[find(a)] = find(b)
    return [find(a) for a in range(n)]


def estimate_balance(values: NDArray[np.float64], valid: NDArray[np.bool_], *, mode: str = "mean",
                     reference: int = 0, names: list[str] | None = None) -> Balance:
    """Gains and offsets from samples of the images at common ground points.

    Parameters
    ----------
    values : (n, m, bands) float64
        Image i's values at sample point k (any value where invalid).
    valid : (n, m) bool
    mode : ``"mean"`` or ``"reference"``
    reference : int
        0-based image kept as it is in ``reference`` mode.
    names : list of str, optional
        Image names for the errors.

    Raises
    ------
    InvalidInputError
        Fewer than 2 images, an image overlapping no other, images in two groups that do not overlap,
        a bad mode or reference.
    """
    v = np.asarray(values, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(v).all(axis=-1)
    n, _m, nb = v.shape
    names = names or [f"image {i + 1}" for i in range(n)]
    if mode not in ("mean", "reference"):
        raise InvalidInputError(f"balance mode must be 'mean' or 'reference'; got {mode!r}")
    if n < 2:
        raise InvalidInputError("radiometric balancing needs at least 2 overlapping orthophotos")
    if not 0 <= reference < n:
        raise InvalidInputError(f"balance reference {reference + 1} out of range 1..{n}")
    pairs: list[tuple[int, int, NDArray[np.intp]]] = []
    for i in range(n):
        for j in range(i + 1, n):
            k = np.flatnonzero(ok[i] & ok[j])
            if k.size >= MIN_COMMON:
                pairs.append((i, j, k))
    linked = {a for i, j, _ in pairs for a in (i, j)}
    for i in range(n):
        if i not in linked:
            raise InvalidInputError(f"orthophoto {names[i]!r} overlaps no other orthophoto (fewer than "
                                    f"{MIN_COMMON} common samples); radiometric balancing needs overlaps")
    comp = _components(n, [(i, j) for i, j, _ in pairs])
    if len(set(comp)) > 1:
        other = next(i for i in range(n) if comp[i] != comp[0])
        raise InvalidInputError(f"orthophotos {names[0]!r} and {names[other]!r} are in groups that do not overlap "
                                f"each other; balance each group on its own")
    gains = np.ones((n, nb))
    offsets = np.zeros((n, nb))
    for b in range(nb):
        N = np.zeros((2 * n, 2 * n))
        for i, j, k in pairs:
            a = np.zeros((k.size, 2 * n))
            a[:, i] = v[i, k, b]
            a[:, n + i] = 1.0
            a[:, j] = -v[j, k, b]
            a[:, n + j] = -1.0
            N += a.T @ a / k.size  # each pair weighs as one, whatever its overlap's size
        if mode == "reference":
            A = np.zeros((2, 2 * n))
            A[0, reference] = 1.0
            A[1, n + reference] = 1.0
            rhs = np.array([1.0, 0.0])
        else:
            A = np.zeros((2, 2 * n))
            A[0, :n] = 1.0
            A[1, n:] = 1.0
            rhs = np.array([float(n), 0.0])
        K = np.block([[N, A.T], [A, np.zeros((2, 2))]])
        x = np.linalg.lstsq(K, np.concatenate([np.zeros(2 * n), rhs]), rcond=None)[0]
        gains[:, b], offsets[:, b] = x[:n], x[n:2 * n]
    stats = []
    for i, j, k in pairs:
        d0 = v[i, k] - v[j, k]
        d1 = (v[i, k] * gains[i] + offsets[i]) - (v[j, k] * gains[j] + offsets[j])
        stats.append(PairStats(i, j, int(k.size), tuple(float(x) for x in np.sqrt((d0 ** 2).mean(axis=0))),
                               tuple(float(x) for x in np.sqrt((d1 ** 2).mean(axis=0)))))
    return Balance(gains, offsets, tuple(stats), mode, reference if mode == "reference" else None)
