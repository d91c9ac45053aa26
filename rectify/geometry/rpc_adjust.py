"""Block adjustment of RPC images: image-space bias compensation (Grodecki and Dial 2003) and its refit.

Model
-----
Each image ``j`` keeps its RPC ``f_j`` (ground (lon, lat, h) -> (col, row), :class:`rectify.geometry.rpc.RPC`)
and gets an image-space correction ``A_j`` of the projected pixel ``p = f_j(X)``::

    p' = p + A_j(p)
    shift :  dc = a0,                        dr = b0
    affine:  dc = a0 + a1 c~ + a2 r~,        dr = b0 + b1 c~ + b2 r~

with ``c~ = (col - c0) / s``, ``r~ = (row - r0) / s`` the pixel normalised on the image (``(c0, r0)`` its
centre, ``s`` half its longer side), so ``a0, b0`` are the correction at the image centre and
``a1, a2, b1, b2`` the corrections at the edge (px). The same correction in the plain pixel frame of
:class:`rectify.geometry.rpc.RPCRefinement` (``dc = a0' + a1' col + a2' row``) is :meth:`RPCBlockAdjustment.refinement`.

Unknowns: the bias parameters of every image and the ground point (lon, lat, h; corrected in metres east,
north, up) of every tie track. Observations:

- image measurements of the tracks (col, row), standard deviation ``sigma_px`` each;
- ground coordinates of the GCPs (tracks with control), standard deviations (east/north, up) in metres;
- a weak prior on every bias parameter: zero with ``prior_px`` (default 10 px). It gives a block without
  GCPs its datum: of the corrections that fit the images equally well (a common shift of every image is
  nearly a shift of the ground), the adjustment takes the one of least weighted norm (about a zero mean
  bias over the images). With GCPs the prior is negligible against them.

Least squares by Gauss-Newton with the ground points eliminated (Schur complement: a 3 x 3 block per
track); robust weights by iteratively reweighted least squares on the standardised residuals
(:mod:`rectify.geometry.robust`, Huber by default); ``sigma0`` from the weighted residuals and the
redundancy; the standard errors of the biases from the reduced normal matrix times ``sigma0^2``.
Check points are left out and intersected afterwards with the adjusted models; their errors (metres,
east/north/up at the point) give an :class:`rectify.geometry.accuracy.AccuracyStatement`.

Refit (:func:`refit_rpc`): an RPC that maps ground to the corrected pixels. A shift folds into the
offsets exactly (``samp_off + a0'``, ``line_off + b0'``). An affine mixes the two ratios of different
denominators, which a rational function of the same form represents only approximately: the
denominators are kept and the numerators refitted by linear least squares on a grid of the RPC's
validity volume; the error is measured on a denser, shifted grid (max and RMS px) and the refit refused
above a tolerance.

Units: pixels (col, row), degrees, metres above the ellipsoid, as the RPC model.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.accuracy import AccuracyStatement
from rectify.geometry.geodesy import ecef_from_geodetic, enu_from_ecef
from rectify.geometry.robust import PSI_FUNCTIONS, ROBUST_METHODS, get_psi
from rectify.geometry.rpc import RPC, RPCRefinement, _monomials

__all__ = ["BIAS_MODELS", "RPCBlockAdjustment", "RefitResult", "TieTracks", "footprint", "check_overlap",
           "chain_matches", "refit_rpc"]

logger = logging.getLogger(__name__)

#: bias model -> number of parameters per image axis
BIAS_MODELS = {"shift": 1, "affine": 3}
_A = 6378137.0
_E2 = 6.69437999014e-3


def _metres_per_degree(lat_deg: NDArray) -> tuple[NDArray, NDArray]:
    """Metres per degree of longitude and latitude on WGS 84 at the latitudes."""
    phi = np.radians(lat_deg)
    w = np.sqrt(1.0 - _E2 * np.sin(phi) ** 2)
    n = _A / w
    m = _A * (1 - _E2) / w ** 3
    return np.radians(1.0) * n * np.cos(phi), np.radians(1.0) * m


@dataclass(frozen=True, eq=False)
class TieTracks:
    """Image measurements of ground points seen in several images.

    Attributes
    ----------
    ids : tuple of str
        One per track (a GCP's track has the GCP's id).
    image : (M,) int64
        Image index of each measurement.
    track : (M,) int64
        Track index of each measurement.
    pixels : (M, 2) float64
        (col, row) measured, px.
    sigma : (M,) float64
        Standard deviation of each measurement (each axis), px.
    """

    ids: tuple[str, ...]
    image: NDArray[np.int64]
    track: NDArray[np.int64]
    pixels: NDArray[np.float64]
    sigma: NDArray[np.float64]

    @classmethod
    def from_arrays(cls, ids: Sequence[str], image: ArrayLike, track: ArrayLike, pixels: ArrayLike,
                    sigma: ArrayLike | float = 0.5) -> TieTracks:
        """Validate and build (``sigma`` a number or one per measurement)."""
        im = np.asarray(image, dtype=np.int64).reshape(-1)
        tr = np.asarray(track, dtype=np.int64).reshape(-1)
        px = np.asarray(pixels, dtype=np.float64)
        if px.ndim != 2 or px.shape != (len(im), 2) or tr.shape != im.shape:
            raise ShapeError(f"tie measurements: image ({im.shape}), track ({tr.shape}) and pixels "
                             f"({px.shape}, expected ({len(im)}, 2)) must agree", actual_shape=px.shape,
                             expected_shape=(len(im), 2))
        sg = np.broadcast_to(np.asarray(sigma, dtype=np.float64), im.shape).copy()
        if not np.isfinite(px).all():
            raise InvalidInputError(f"tie measurement {int(np.flatnonzero(~np.isfinite(px).all(1))[0])} is not finite")
        if not (np.isfinite(sg).all() and (sg > 0).all()):
            raise InvalidInputError(f"tie measurement sigmas must be finite and > 0; got {sg[~(sg > 0)][:1].tolist()}")
        names = tuple(str(i) for i in ids)
        if len(im) and (tr.min() < 0 or tr.max() >= len(names)):
            raise InvalidInputError(f"tie measurement track index out of range 0..{len(names) - 1}")
        for a in (im, tr, px, sg):
            a.flags.writeable = False
        return cls(names, im, tr, px, sg)

    def __len__(self) -> int:
        return len(self.image)

    def select(self, keep: NDArray[np.bool_]) -> TieTracks:
        """The measurements ``keep`` (M,) bool, tracks renumbered (empty tracks dropped)."""
        tr = self.track[keep]
        used = np.unique(tr)
        remap = np.full(len(self.ids), -1, np.int64)
        remap[used] = np.arange(len(used))
        return TieTracks.from_arrays([self.ids[i] for i in used], self.image[keep], remap[tr],
                                     self.pixels[keep], self.sigma[keep])


def footprint(rpc: RPC, size: tuple[int, int], height: float | None = None) -> NDArray[np.float64]:
    """Ground corners (4, 2) (lon, lat) of an image of ``size`` (width, height) px at a height (default the
    RPC's height offset)."""
    w, h = size
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
    return rpc.localize(corners, rpc.height_off if height is None else height)[:, :2]


def _overlap(a: NDArray, b: NDArray) -> bool:
    """Whether two convex quadrilaterals (4, 2) overlap (separating axis test)."""
    for poly in (a, b):
        for i in range(4):
            e = poly[(i + 1) % 4] - poly[i]
            n = np.array([-e[1], e[0]])
            pa, pb = a @ n, b @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def check_overlap(rpcs: Sequence[RPC], sizes: Sequence[tuple[int, int]], names: Sequence[str]
                  ) -> list[tuple[int, int]]:
    """The pairs (i, j), i < j, of images whose ground footprints (at the mean RPC height offset) overlap.

    Raises
    ------
    InvalidInputError
        Fewer than 2 images, or the footprints do not form one connected block (names the first image
        that overlaps none of the others / the first cut-off group).
    """
    n = len(rpcs)
    if n < 2:
        raise InvalidInputError(f"an RPC block adjustment needs at least 2 images; got {n}")
    h = float(np.mean([r.height_off for r in rpcs]))
    fps = [footprint(r, s, h) for r, s in zip(rpcs, sizes, strict=True)]
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if _overlap(fps[i], fps[j])]
    for i in range(n):
        if not any(i in p for p in pairs):
            lo, la = fps[i].mean(axis=0)
            raise InvalidInputError(f"image {names[i]!r} does not overlap any other image (its footprint at "
                                    f"{h:.0f} m is centred at lon {lo:.5f}, lat {la:.5f})")
    _check_connected(n, pairs, names, "footprints")
    return pairs


def _check_connected(n: int, pairs: Sequence[tuple[int, int]], names: Sequence[str], what: str) -> None:
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    for i, j in pairs:
        parent[find(i)] = find(j)
    roots = {find(i) for i in range(n)}
    if len(roots) > 1:
        cut = [names[i] for i in range(n) if find(i) != find(0)]
        raise InvalidInputError(f"the images do not form one block by their {what}: {cut} are not connected "
                                f"to {names[0]!r}")


def chain_matches(pairs: Sequence[tuple[int, int, NDArray, NDArray]], *, radius_px: float = 0.5, prefix: str = "t"
                  ) -> tuple[tuple[str, ...], NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Multi-image tracks from pairwise matches.

    ``pairs``: (i, j, left (K, 2), right (K, 2)) with the matches of image ``i`` (left) and image ``j``
    (right). Measurements of one image closer than ``radius_px`` are one point; a track is a connected
    set of points and matches. A track that holds two points of one image farther apart than
    ``2 radius_px`` is dropped (an ambiguous chain); the points of one image within it are averaged.

    Returns
    -------
    ids (T,), image (M,), track (M,), pixels (M, 2): the measurements of the tracks of 2 or more images.
    """
    pos, img, edges = [], [], []
    k = 0
    for i, j, pl, pr in pairs:
        pl = np.asarray(pl, np.float64).reshape(-1, 2)
        pr = np.asarray(pr, np.float64).reshape(-1, 2)
        m = len(pl)
        pos += [pl, pr]
        img += [np.full(m, i), np.full(m, j)]
        edges.append(np.column_stack([k + np.arange(m), k + m + np.arange(m)]))
        k += 2 * m
    if k == 0:
        return (), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    P = np.vstack(pos)
    im_all = np.concatenate(img).astype(np.int64)
    E = [np.vstack(edges)]
    for j in np.unique(im_all):
        idx = np.flatnonzero(im_all == j)
        near = cKDTree(P[idx]).query_pairs(radius_px, output_type="ndarray")
        if len(near):
            E.append(idx[near])
    e = np.vstack(E)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(k, k))
    _n, comp = connected_components(graph, directed=False)
    n_img = int(im_all.max()) + 1
    key = comp.astype(np.int64) * n_img + im_all
    uk, inv = np.unique(key, return_inverse=True)
    cnt = np.bincount(inv)
    mean = np.column_stack([np.bincount(inv, P[:, 0]) / cnt, np.bincount(inv, P[:, 1]) / cnt])
    spread = np.zeros(len(uk))
    np.maximum.at(spread, inv, np.hypot(*(P - mean[inv]).T))
    tr_of = uk // n_img
    bad_tracks = np.unique(tr_of[spread > 2 * radius_px])
    ok = ~np.isin(tr_of, bad_tracks)
    n_images = np.bincount(tr_of[ok], minlength=int(comp.max()) + 1)
    ok &= n_images[tr_of] >= 2
    tr_ok, im_ok, px_ok = tr_of[ok], (uk % n_img)[ok], mean[ok]
    used, track = np.unique(tr_ok, return_inverse=True)
    ids = tuple(f"{prefix}{t + 1}" for t in range(len(used)))
    return ids, im_ok.astype(np.int64), track.astype(np.int64), px_ok


# ============================================================================= the adjustment
def _design(pn: NDArray, k: int) -> NDArray[np.float64]:
    """(M, 2, 2k) derivative of the correction (dc, dr) with respect to (a..., b...) at normalised pixels."""
    m = len(pn)
    D = np.zeros((m, 2, 2 * k))
    D[:, 0, 0] = D[:, 1, k] = 1.0
    if k == 3:
        D[:, 0, 1], D[:, 0, 2] = pn[:, 0], pn[:, 1]
        D[:, 1, 4], D[:, 1, 5] = pn[:, 0], pn[:, 1]
    return D


class _Block:
    """The fixed parts of one adjustment: models, normalisation, measurements."""

    def __init__(self, rpcs: Sequence[RPC], sizes: Sequence[tuple[int, int]], model: str) -> None:
        self.rpcs = list(rpcs)
        self.k = BIAS_MODELS[model]
        self.model = model
        sz = np.asarray(sizes, dtype=np.float64)
        self.centre = np.column_stack([(sz[:, 0] - 1) / 2, (sz[:, 1] - 1) / 2])
        self.half = sz.max(axis=1) / 2

    def project(self, ground: NDArray, image: NDArray) -> NDArray[np.float64]:
        """Plain RPC pixels (M, 2) of ground (M, 3) in the images (M,)."""
        out = np.empty((len(ground), 2))
        for j in np.unique(image):
            s = image == j
            out[s] = self.rpcs[j]._project(ground[s])
        return out

    def normalise(self, px: NDArray, image: NDArray) -> NDArray[np.float64]:
        return (px - self.centre[image]) / self.half[image][:, None]

    def corrected(self, theta: NDArray, ground: NDArray, image: NDArray
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Corrected pixels (M, 2) and the design (M, 2, 2k) of the bias parameters there."""
        p = self.project(ground, image)
        D = _design(self.normalise(p, image), self.k)
        return p + np.einsum("mij,mj->mi", D, theta[image]), D

    def jacobian(self, theta: NDArray, ground: NDArray, image: NDArray) -> NDArray[np.float64]:
        """d(corrected pixel)/d(east, north, up metres) (M, 2, 3), central differences of 0.5 m."""
        mx, my = _metres_per_degree(ground[:, 1])
        J = np.empty((len(ground), 2, 3))
        for a, step in enumerate((0.5 / mx, 0.5 / my, np.full(len(ground), 0.5))):
            dg = np.zeros_like(ground)
            dg[:, a] = step
            hi, _ = self.corrected(theta, ground + dg, image)
            lo, _ = self.corrected(theta, ground - dg, image)
            J[:, :, a] = (hi - lo) / 1.0
        return J


def _solve3(V: NDArray, g: NDArray) -> NDArray[np.float64]:
    """Solve the (T, 3, 3) systems V x = g (T, 3)."""
    return np.linalg.solve(V, g[..., None])[..., 0]


def _intersect(block: _Block, theta: NDArray, obs: TieTracks, ground0: NDArray, w: NDArray,
               iterations: int = 15) -> NDArray[np.float64]:
    """Ground points (T, 3) of the tracks with the biases fixed (Gauss-Newton per track)."""
    g = ground0.copy()
    T = len(g)
    for _ in range(iterations):
        pc, _ = block.corrected(theta, g[obs.track], obs.image)
        r = obs.pixels - pc
        J = block.jacobian(theta, g[obs.track], obs.image)
        wt = (w / obs.sigma ** 2)[:, None, None]
        V = np.zeros((T, 3, 3))
        gv = np.zeros((T, 3))
        np.add.at(V, obs.track, np.einsum("mia,mib->mab", J, wt * J))
        np.add.at(gv, obs.track, np.einsum("mia,mi->ma", J, wt[:, :, 0] * r))
        V += np.eye(3) * 1e-9
        d = _solve3(V, gv)
        g = _apply_metres(g, d)
        if np.abs(d).max() < 1e-5:
            break
    return g


def _apply_metres(g: NDArray, d: NDArray) -> NDArray[np.float64]:
    mx, my = _metres_per_degree(g[:, 1])
    return g + np.column_stack([d[:, 0] / mx, d[:, 1] / my, d[:, 2]])


def _start(block: _Block, obs: TieTracks, n_tracks: int) -> NDArray[np.float64]:
    """Starting ground points: the first measurement localised at its RPC's height offset, then intersected."""
    first = np.full(n_tracks, -1, np.int64)
    order = np.arange(len(obs))[::-1]
    first[obs.track[order]] = order  # the smallest index wins
    g = np.empty((n_tracks, 3))
    for j in np.unique(obs.image[first]):
        s = obs.image[first] == j
        rpc = block.rpcs[j]
        g[s] = rpc.localize(obs.pixels[first[s]], rpc.height_off, on_failure="nan")
    if not np.isfinite(g).all():
        i = int(np.flatnonzero(~np.isfinite(g).all(1))[0])
        raise EstimationError(f"tie track {obs.ids[i]!r} cannot be localised in its first image")
    return _intersect(block, np.zeros((len(block.rpcs), 2 * block.k)), obs, g, np.ones(len(obs)))


@dataclass(frozen=True, eq=False)
class RPCBlockAdjustment:
    """The adjusted bias corrections of a block of RPC images (see the module docstring).

    Attributes
    ----------
    rpcs : tuple of RPC
    sizes : tuple of (width, height)
    model : ``"shift"`` or ``"affine"``
    params : (N, 2, k) float64
        Bias parameters per image: row 0 the column correction (a0[, a1, a2]), row 1 the row correction
        (b0[, b1, b2]), px, in the normalised pixel frame (a0, b0 at the image centre).
    std : (N, 2, k) float64
        Their standard errors, px (``sigma0`` times the reduced normal matrix's inverse).
    sigma0 : float
        Standard deviation of unit weight (a posteriori), unitless (1 when ``sigma_px`` and the GCP sigmas are right).
    redundancy : int
    tracks : TieTracks
        The measurements adjusted (check points left out).
    ground : (T, 3) float64
        Adjusted ground points of the tracks (lon, lat, h).
    residuals : (M, 2) float64
        Adjusted minus measured pixels, px (the project's residual sign).
    weights : (M,) float64
        Final robust weights (1 without robust weighting).
    control_ids : tuple of str
    control_residuals : (G, 3) float64
        Adjusted minus surveyed ground of the GCPs, metres east, north, up.
    check_ids : tuple of str
    check_errors : (C, 3) float64
        Intersected (with the adjusted models) minus surveyed check points, metres east, north, up.
    accuracy : AccuracyStatement or None
        Of the check points (None without).
    iterations : int
    robust : str
    cov : (N 2k, N 2k) float64
        Covariance of the bias parameters (image-major, then the column's then the row's), px^2.
    """

    rpcs: tuple[RPC, ...]
    sizes: tuple[tuple[int, int], ...]
    model: str
    params: NDArray[np.float64]
    std: NDArray[np.float64]
    sigma0: float
    redundancy: int
    tracks: TieTracks
    ground: NDArray[np.float64]
    residuals: NDArray[np.float64]
    weights: NDArray[np.float64]
    control_ids: tuple[str, ...]
    control_residuals: NDArray[np.float64]
    check_ids: tuple[str, ...]
    check_errors: NDArray[np.float64]
    accuracy: AccuracyStatement | None
    iterations: int
    robust: str
    cov: NDArray[np.float64]

    @classmethod
    def from_observations(cls, rpcs: Sequence[RPC], sizes: Sequence[tuple[int, int]], tracks: TieTracks, *,
                          control: dict[str, tuple[Sequence[float], Sequence[float]]] | None = None,
                          check: Sequence[str] = (), model: str = "shift", prior_px: float = 10.0,
                          robust: str = "huber", max_iter: int = 60, names: Sequence[str] | None = None
                          ) -> RPCBlockAdjustment:
        """Adjust the block.

        Parameters
        ----------
        rpcs : N RPC models; sizes : N (width, height) px
        tracks : TieTracks
            Tie and GCP measurements (image indexes 0..N-1).
        control : {id: ((lon, lat, h), (sigma_en_m, sigma_u_m))}
            Surveyed ground points (WGS 84 degrees, ellipsoidal metres) of the tracks of the same id.
        check : ids of ``control`` used as check points (left out of the adjustment).
        model : ``"shift"`` or ``"affine"``
        prior_px : standard deviation of the zero prior of every bias parameter, px.
        robust : ``"none"`` or a psi function name (:data:`rectify.geometry.robust.ROBUST_METHODS`).

        Raises
        ------
        InvalidInputError
            Unknown model or robust method, bad prior, a check id that is no GCP, an image without
            measurements, tie tracks that do not connect the images.
        EstimationError
            The normal equations are singular, or a track cannot be intersected.
        """
        if model not in BIAS_MODELS:
            raise InvalidInputError(f"unknown bias model {model!r}; expected one of {list(BIAS_MODELS)}")
        if robust not in ROBUST_METHODS:
            raise InvalidInputError(f"unknown robust method {robust!r}; expected one of {list(ROBUST_METHODS)}")
        if not (math.isfinite(prior_px) and prior_px > 0):
            raise InvalidInputError(f"prior_px must be a finite number > 0; got {prior_px!r}")
        n = len(rpcs)
        if len(sizes) != n:
            raise ShapeError(f"{n} RPCs but {len(sizes)} image sizes")
        names = [f"image {j}" for j in range(n)] if names is None else list(names)
        control = dict(control or {})
        chk = set(map(str, check))
        for c in chk:
            if c not in control:
                raise InvalidInputError(f"check point {c!r} is not a GCP (GCP ids: {sorted(control)[:10]})")
        if len(tracks) and (tracks.image.min() < 0 or tracks.image.max() >= n):
            raise InvalidInputError(f"tie measurement image index out of range 0..{n - 1}")
        is_check = np.array([tracks.ids[t] in chk for t in tracks.track], bool)
        adj_obs = tracks.select(~is_check)
        chk_obs = tracks.select(is_check)
        # every adjusted track needs two images (or a GCP and one image)
        cnt = np.bincount(adj_obs.track, minlength=len(adj_obs.ids))
        ctrl_t = np.array([i in control for i in adj_obs.ids], bool)
        keep = (cnt >= 2) | ctrl_t
        adj_obs = adj_obs.select(keep[adj_obs.track])
        _check_images(adj_obs, n, names, BIAS_MODELS[model])
        block = _Block(rpcs, sizes, model)
        k = block.k
        P = n * 2 * k
        T = len(adj_obs.ids)
        ctrl_idx = np.array([t for t, i in enumerate(adj_obs.ids) if i in control], np.int64)
        ctrl_g = np.array([control[adj_obs.ids[t]][0] for t in ctrl_idx], np.float64).reshape(-1, 3)
        ctrl_s = np.array([[control[adj_obs.ids[t]][1][0]] * 2 + [control[adj_obs.ids[t]][1][1]]
                           for t in ctrl_idx], np.float64).reshape(-1, 3)
        if len(ctrl_s) and not ((ctrl_s > 0) & np.isfinite(ctrl_s)).all():
            raise InvalidInputError("GCP sigmas must be finite numbers > 0")
        psi = None if robust == "none" else get_psi(robust)
        n_t = np.bincount(adj_obs.track, minlength=T)
        q = np.clip((2 * n_t - 3 + 3 * np.isin(np.arange(T), ctrl_idx)) / (2 * n_t), 0.1, 1.0)[adj_obs.track]
        scale = 1.0
        w = np.ones(len(adj_obs))
        theta = np.zeros((n, 2 * k))
        g = _start(block, adj_obs, T)
        if len(ctrl_idx):
            g[ctrl_idx] = ctrl_g
        prior_w = 1.0 / prior_px ** 2
        it = 0
        cov = np.zeros((P, P))
        for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
            pc, D = block.corrected(theta, g[adj_obs.track], adj_obs.image)
            r = adj_obs.pixels - pc
            w_prev = w
            if psi is not None and it > 2:
                # squared residual norm over the measurement's share of its track's redundancy: about
                # sigma0^2 chi2(2); its scale from the median (chi2(2)'s median is 2 ln 2), frozen after 6 rounds
                z = np.sum((r / adj_obs.sigma[:, None]) ** 2, axis=1) / q
                if it <= 6:
                    # floored at 1 % of the given sigmas: an exact fit is not a reason to reject measurements
                    scale = max(math.sqrt(float(np.median(z[w > 0])) / (2 * math.log(2))), 0.01)
                # a redescending psi starts from Huber's weights (it may reject good points from a poor start)
                first = PSI_FUNCTIONS["huber"] if it <= 6 and math.isfinite(psi.rejection_point) else psi
                w = first.weight(np.sqrt(z / 2) / scale)
            J = block.jacobian(theta, g[adj_obs.track], adj_obs.image)
            wt = (w / adj_obs.sigma ** 2)[:, None]
            # per-track blocks
            V = np.zeros((T, 3, 3))
            gv = np.zeros((T, 3))
            np.add.at(V, adj_obs.track, np.einsum("mia,mib->mab", J, wt[:, :, None] * J))
            np.add.at(gv, adj_obs.track, np.einsum("mia,mi->ma", J, wt * r))
            if len(ctrl_idx):
                mx, my = _metres_per_degree(g[ctrl_idx, 1])
                dctrl = np.column_stack([(ctrl_g[:, 0] - g[ctrl_idx, 0]) * mx, (ctrl_g[:, 1] - g[ctrl_idx, 1]) * my,
                                         ctrl_g[:, 2] - g[ctrl_idx, 2]])
                V[ctrl_idx] += np.einsum("ta,ab->tab", 1.0 / ctrl_s ** 2, np.eye(3))
                gv[ctrl_idx] += dctrl / ctrl_s ** 2
            # bias blocks: U (P, P), W (T, P, 3), gu (P,)
            cols = adj_obs.image[:, None] * 2 * k + np.arange(2 * k)[None, :]  # (M, 2k)
            DtD = np.einsum("mia,mib->mab", D, wt[:, :, None] * D)
            U = np.zeros((P, P))
            for j in range(n):
                s = adj_obs.image == j
                U[j * 2 * k:(j + 1) * 2 * k, j * 2 * k:(j + 1) * 2 * k] = DtD[s].sum(axis=0)
            U += prior_w * np.eye(P)
            gu = np.zeros(P)
            np.add.at(gu, cols, np.einsum("mia,mi->ma", D, wt * r))
            gu -= prior_w * theta.ravel()
            Wm = np.einsum("mia,mib->mab", D, wt[:, :, None] * J)  # (M, 2k, 3)
            Wt = np.zeros((T, P, 3))
            np.add.at(Wt, (adj_obs.track[:, None], cols), Wm)
            V += 1e-9 * np.eye(3)  # a track whose measurements all lost their weight (redescending psi) stays put
            try:
                Vi = np.linalg.inv(V)
            except np.linalg.LinAlgError:
                raise EstimationError("a tie track's ground point is undetermined (singular 3 x 3 block)") from None
            WVi = np.einsum("tpa,tab->tpb", Wt, Vi)
            S = U - np.einsum("tpa,tqa->pq", WVi, Wt)
            rhs = gu - np.einsum("tpa,ta->p", WVi, gv)
            try:
                cov = np.linalg.inv(S)
            except np.linalg.LinAlgError:
                raise EstimationError("the reduced normal equations of the biases are singular") from None
            if not np.isfinite(cov).all() or np.linalg.cond(S) > 1e14:
                raise EstimationError(f"the reduced normal equations of the biases are near singular "
                                      f"(condition {np.linalg.cond(S):.1e})")
            dth = cov @ rhs
            dX = np.einsum("tab,tb->ta", Vi, gv - np.einsum("tpa,p->ta", Wt, dth))
            theta = theta + dth.reshape(n, 2 * k)
            g = _apply_metres(g, dX)
            logger.debug("iteration %d: bias step %.3g px, ground step %.3g m, weight change %.3g", it,
                         np.abs(dth).max(), np.abs(dX).max(), np.abs(w - w_prev).max())
            # the biases to 1e-5 px; ground points (which move little against a pixel of ~0.5 m) to 1 cm, weights
            # to 0.01 (the tail of a few down-weighted tracks converges linearly and changes no bias)
            small = np.abs(dth).max() < 1e-5 and np.abs(dX).max() < 1e-2
            if small and (psi is None or (it > 6 and np.abs(w - w_prev).max() < 1e-2)):
                break
        else:
            logger.warning("RPC block adjustment stopped after %d iterations without converging", max_iter)
        pc, _ = block.corrected(theta, g[adj_obs.track], adj_obs.image)
        res = pc - adj_obs.pixels
        vtpv = float(np.sum(w[:, None] * (res / adj_obs.sigma[:, None]) ** 2)) + prior_w * float(np.sum(theta ** 2))
        cres = np.zeros((len(ctrl_idx), 3))
        if len(ctrl_idx):
            mx, my = _metres_per_degree(g[ctrl_idx, 1])
            cres = np.column_stack([(ctrl_g[:, 0] - g[ctrl_idx, 0]) * mx, (ctrl_g[:, 1] - g[ctrl_idx, 1]) * my,
                                    ctrl_g[:, 2] - g[ctrl_idx, 2]])
            vtpv += float(np.sum((cres / ctrl_s) ** 2))
            cres = -cres  # adjusted minus surveyed
        n_obs = 2 * int((w > 0).sum()) + 3 * len(ctrl_idx) + P
        redundancy = n_obs - P - 3 * T
        if redundancy <= 0:
            raise EstimationError(f"the block has no redundancy ({n_obs} observations, {P + 3 * T} unknowns): "
                                  "more tie points are needed")
        sigma0 = math.sqrt(vtpv / redundancy)
        std = np.sqrt(np.clip(np.diag(cov), 0, None)) * sigma0
        # check points: intersected with the adjusted biases
        cids: tuple[str, ...] = ()
        cerr = np.zeros((0, 3))
        acc = None
        if len(chk_obs):
            cnt = np.bincount(chk_obs.track, minlength=len(chk_obs.ids))
            if (cnt < 2).any():
                bad = chk_obs.ids[int(np.flatnonzero(cnt < 2)[0])]
                raise InvalidInputError(f"check point {bad!r} is measured in fewer than 2 images; it cannot be "
                                        "intersected")
            g0 = _start(block, chk_obs, len(chk_obs.ids))
            gc = _intersect(block, theta, chk_obs, g0, np.ones(len(chk_obs)))
            truth = np.array([control[i][0] for i in chk_obs.ids], np.float64)
            cerr = np.vstack([enu_from_ecef(ecef_from_geodetic(gc[i:i + 1]), truth[i]) for i in range(len(gc))])
            cids = chk_obs.ids
            acc = AccuracyStatement.from_errors(cerr, units="m")
        logger.info("RPC block adjustment (%s): %d images, %d tracks, sigma0 %.3f after %d iterations", model, n, T,
                    sigma0, it)
        return cls(tuple(rpcs), tuple((int(a), int(b)) for a, b in sizes), model,
                   theta.reshape(n, 2, k), std.reshape(n, 2, k), sigma0, redundancy, adj_obs, g, res, w,
                   tuple(adj_obs.ids[t] for t in ctrl_idx), cres, cids, cerr, acc, it, robust, cov * sigma0 ** 2)

    # ------------------------------------------------------------------ derived
    def plain_params(self, j: int) -> NDArray[np.float64]:
        """Image ``j``'s correction in the plain pixel frame of :class:`RPCRefinement` (2, k)."""
        p = self.params[j]
        if self.model == "shift":
            return p.copy()
        w, h = self.sizes[j]
        c0, r0, s = (w - 1) / 2, (h - 1) / 2, max(w, h) / 2
        Tm = np.array([[1.0, -c0 / s, -r0 / s], [0.0, 1.0 / s, 0.0], [0.0, 0.0, 1.0 / s]])
        return p @ Tm.T

    def refinement(self, j: int) -> RPCRefinement:
        """Image ``j``'s adjusted projection (RPC + bias) as an :class:`RPCRefinement`."""
        return RPCRefinement(self.rpcs[j], self.model, self.plain_params(j))

    def relative_std(self, j: int, ref: int = 0) -> NDArray[np.float64]:
        """Standard errors (2, k) of image ``j``'s parameters minus image ``ref``'s, px: free of the datum
        (without GCPs the absolute standard errors are mostly the prior's)."""
        m = 2 * BIAS_MODELS[self.model]
        a, b = slice(j * m, (j + 1) * m), slice(ref * m, (ref + 1) * m)
        c = self.cov[a, a] + self.cov[b, b] - self.cov[a, b] - self.cov[b, a]
        return np.sqrt(np.clip(np.diag(c), 0, None)).reshape(2, -1)

    def image_rms(self) -> NDArray[np.float64]:
        """RMS of the residuals per image (N, 2), px (measurements with weight > 0)."""
        out = np.full((len(self.rpcs), 2), np.nan)
        for j in range(len(self.rpcs)):
            s = (self.tracks.image == j) & (self.weights > 0)
            if s.any():
                out[j] = np.sqrt(np.mean(self.residuals[s] ** 2, axis=0))
        return out


def _check_images(obs: TieTracks, n: int, names: Sequence[str], k: int) -> None:
    """Every image has measurements and the tracks connect the images."""
    cnt = np.bincount(obs.image, minlength=n)
    need = max(3, 2 * k)
    for j in range(n):
        if cnt[j] < need:
            raise InvalidInputError(f"image {names[j]!r} has {int(cnt[j])} tie measurements; the adjustment needs at "
                                    f"least {need} per image")
    pairs: set[tuple[int, int]] = set()
    order = np.argsort(obs.track, kind="stable")
    tr, im = obs.track[order], obs.image[order]
    starts = np.flatnonzero(np.r_[True, tr[1:] != tr[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], len(tr)], strict=True):
        ims = np.unique(im[a:b])
        pairs.update((int(ims[0]), int(x)) for x in ims[1:])
    _check_connected(n, sorted(pairs), names, "tie points")


# ============================================================================= refit
@dataclass(frozen=True)
class RefitResult:
    """A refitted RPC and its error against the compensated model.

    Attributes
    ----------
    rpc : RPC
    max_px, rms_px : float
        Max and RMS of the distance between the refitted RPC and the compensated model, px, over the check
        grid (a denser grid shifted against the fitting grid).
    method : str
        ``"offsets"`` (exact fold of a shift) or ``"numerators"`` (least squares, denominators kept).
    n_check : int
        Points of the check grid.
    """

    rpc: RPC
    max_px: float
    rms_px: float
    method: str
    n_check: int


def _grid(rpc: RPC, n_xy: int, n_h: int, shift: float = 0.0) -> NDArray[np.float64]:
    """A grid of the validity volume (lon, lat, h), optionally shifted by ``shift`` cells (kept inside)."""
    (x0, x1), (y0, y1), (z0, z1) = rpc.validity_box

    def axis(a: float, b: float, m: int) -> NDArray:
        t = (np.arange(m) + shift) / (m - 1 + (1 if shift else 0))
        return a + (b - a) * t
    lo, la, hh = np.meshgrid(axis(x0, x1, n_xy), axis(y0, y1, n_xy), axis(z0, z1, n_h), indexing="ij")
    return np.column_stack([lo.ravel(), la.ravel(), hh.ravel()])


def refit_rpc(ref: RPCRefinement, *, tolerance_px: float = 0.01, n_xy: int = 21, n_h: int = 11,
              source: str | None = None) -> RefitResult:
    """An RPC with ``ref``'s projection (RPC + image-space bias), its refit error measured.

    A shift is folded into the offsets (exact). Otherwise (drift, affine) the denominators are kept and
    the numerators refitted by linear least squares on an ``n_xy`` x ``n_xy`` x ``n_h`` grid of the validity
    volume; the error is measured on a grid of twice the density shifted by half a cell.

    Raises
    ------
    InvalidInputError
        A tolerance that is not a finite number > 0.
    EstimationError
        The refit error exceeds ``tolerance_px`` (the message gives the max error and the tolerance).
    """
    if not (math.isfinite(tolerance_px) and tolerance_px > 0):
        raise InvalidInputError(f"the refit tolerance must be a finite number > 0 px; got {tolerance_px!r}")
    rpc = ref.rpc
    name = source or rpc.source
    d = rpc.to_dict()
    d.update(err_bias=None, err_rand=None)
    if ref.model == "shift":
        d["samp_off"] = rpc.samp_off + float(ref.params[0, 0])
        d["line_off"] = rpc.line_off + float(ref.params[1, 0])
        out = RPC.from_dict(d, source=name)
        method = "offsets"
    else:
        g = _grid(rpc, n_xy, n_h)
        target = ref._project(g)
        L, Pp, H = rpc._normalise(g)
        m = _monomials(L, Pp, H)
        for key, den, off, scale, col in (("samp_num_coeff", rpc.samp_den_coeff, rpc.samp_off, rpc.samp_scale, 0),
                                          ("line_num_coeff", rpc.line_den_coeff, rpc.line_off, rpc.line_scale, 1)):
            y = (target[:, col] - off) / scale
            A = m
            b = y * (m @ den)
            mn = np.abs(A).max(axis=0)
            mn[mn == 0] = 1.0
            sol, *_ = np.linalg.lstsq(A / mn, b, rcond=None)
            d[key] = (sol / mn).tolist()
        out = RPC.from_dict(d, source=name)
        method = "numerators"
    gc = _grid(rpc, 2 * n_xy, 2 * n_h - 1, shift=0.5)
    err = np.hypot(*(out._project(gc) - ref._project(gc)).T)
    ok = np.isfinite(err)
    mx = float(err[ok].max()) if ok.any() else float("inf")
    rmsv = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("inf")
    if not ok.all():
        mx = float("inf")
    if not mx <= tolerance_px:
        raise EstimationError(f"the refitted RPC of {name} cannot reach the tolerance: max error {mx:.3g} px "
                              f"> {tolerance_px:g} px over its validity volume")
    return RefitResult(out, mx, rmsv, method, len(gc))
