"""Rational polynomial camera (RPC) models of satellite images.

Pixel convention
----------------
One convention, the project's: pixel coordinates are ``(N, 2)`` float64
``(col, row)``, x = column (right), y = row (down), the centre of the top-left
pixel at (0, 0). An RPC00B model evaluates ``sample`` and ``line`` with its
own offsets and scales; for RPCs read from GeoTIFF tags, ``_RPC.TXT``, ``.RPB``
and DigitalGlobe XML, ``col = sample`` and ``row = line`` (RPC00B counts the
centre of the first pixel as 0). DIMAP v2 (Pleiades, SPOT 6/7) counts the
first pixel as (1, 1): its LINE_OFF / SAMP_OFF are reduced by 1 on reading, as
GDAL's DIMAP reader and rpcm do, so the stored model obeys the same rule.

GDAL's RPC transformer (``gdalwarp -rpc``, rasterio's ``RPCTransformer``) works
in GDAL's pixel/line frame, where (0, 0) is the *corner* of the top-left pixel:
``gdal_pixel = col + 0.5`` and ``gdal_line = row + 0.5`` (measured in
``tests/rectify/test_rpc.py::test_gdal_half_pixel_convention``).

Ground coordinates are ``(N, 3)`` (lon, lat, h): degrees on WGS 84 and heights
above the ellipsoid (see :mod:`rectify.raster.dem` for geoid heights).

The model, its fit and its refinement live here (formulas); the file readers (``_RPC.TXT``, ``.RPB``,
DIMAP and DigitalGlobe XML, GeoTIFF RPC tags) are in :mod:`rectify.formats.rpc`.

Main entry points: :func:`rectify.formats.rpc.read_rpc` (any of the formats), :meth:`RPC.project`
(ground -> image, vectorised), :meth:`RPC.localize` (image -> ground at given
heights, Newton iteration), :meth:`RPC.localize_on_dem` (image -> the visible
ground of a DEM), :meth:`RPCRefinement.from_gcps` (image-space bias
compensation with leave-one-out check errors).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError, ShapeError
from rectify.geometry.residuals import ResidualTable, rms

__all__ = ["RPC", "RPC_SCALARS", "RPC_COEFFICIENTS", "RPCRefinement", "REFINEMENT_MODELS", "GDAL_PIXEL_OFFSET",
           "fit_rpc"]

logger = logging.getLogger(__name__)

#: GDAL pixel/line = project (col, row) + GDAL_PIXEL_OFFSET (GDAL's (0, 0) is a pixel corner).
GDAL_PIXEL_OFFSET = 0.5

#: The scalar keys of an RPC00B model (rasterio's ``RPC.to_dict`` names) and its four lists of 20 coefficients.
RPC_SCALARS = ("line_off", "samp_off", "lat_off", "long_off", "height_off",
               "line_scale", "samp_scale", "lat_scale", "long_scale", "height_scale")
RPC_COEFFICIENTS = ("line_num_coeff", "line_den_coeff", "samp_num_coeff", "samp_den_coeff")


def _monomials(L: NDArray, P: NDArray, H: NDArray) -> NDArray[np.float64]:
    """The 20 RPC00B terms (N, 20) of normalised lon L, lat P, height H."""
    one = np.ones_like(L)
    return np.stack([one, L, P, H, L * P, L * H, P * H, L * L, P * P, H * H,
                     P * L * H, L ** 3, L * P * P, L * H * H, L * L * P, P ** 3, P * H * H,
                     L * L * H, P * P * H, H ** 3], axis=-1)


def _d_monomials(L: NDArray, P: NDArray, H: NDArray) -> tuple[NDArray, NDArray]:
    """Derivatives of the 20 terms with respect to L and P, each (N, 20)."""
    z, one = np.zeros_like(L), np.ones_like(L)
    dL = np.stack([z, one, z, z, P, H, z, 2 * L, z, z,
                   P * H, 3 * L * L, P * P, H * H, 2 * L * P, z, z, 2 * L * H, z, z], axis=-1)
    dP = np.stack([z, z, one, z, L, z, H, z, 2 * P, z,
                   L * H, z, 2 * L * P, z, L * L, 3 * P * P, H * H, z, 2 * P * H, z], axis=-1)
    return dL, dP


def _as_ground(ground: ArrayLike, name: str = "ground") -> NDArray[np.float64]:
    g = np.asarray(ground, dtype=np.float64)
    if g.ndim == 1 and g.shape[0] == 3:
        g = g[None, :]
    if g.ndim != 2 or g.shape[1] != 3:
        raise ShapeError(f"`{name}` must be (N, 3) (lon, lat, h); got shape {np.shape(ground)}",
                         actual_shape=np.shape(ground), expected_shape=(None, 3))
    return g


def _as_pixels(pixels: ArrayLike, name: str = "pixels") -> NDArray[np.float64]:
    p = np.asarray(pixels, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == 2:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 2:
        raise ShapeError(f"`{name}` must be (N, 2) (col, row); got shape {np.shape(pixels)}",
                         actual_shape=np.shape(pixels), expected_shape=(None, 2))
    return p


@dataclass(frozen=True, eq=False)
class RPC:
    """An RPC00B model: ground (lon, lat, h) -> image (col, row).

    Attributes
    ----------
    line_off, samp_off, lat_off, long_off, height_off : float
        Offsets (line/samp in the project's pixel frame, see the module doc).
    line_scale, samp_scale, lat_scale, long_scale, height_scale : float
        Scales (non-zero).
    line_num_coeff, line_den_coeff, samp_num_coeff, samp_den_coeff : (20,) float64
        Coefficients in RPC00B term order.
    err_bias, err_rand : float or None
        Stated errors (m), when the file has them.
    source : str
        Where the model came from (for messages).
    """

    line_off: float
    samp_off: float
    lat_off: float
    long_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    long_scale: float
    height_scale: float
    line_num_coeff: NDArray[np.float64]
    line_den_coeff: NDArray[np.float64]
    samp_num_coeff: NDArray[np.float64]
    samp_den_coeff: NDArray[np.float64]
    err_bias: float | None = None
    err_rand: float | None = None
    source: str = "RPC"

    def __post_init__(self) -> None:
        for k in RPC_SCALARS:
            v = getattr(self, k)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise InvalidInputError(f"RPC {self.source}: `{k}` must be a number; got {v!r}") from None
            if not math.isfinite(v):
                raise InvalidInputError(f"RPC {self.source}: `{k}` must be finite; got {v!r}")
            if k.endswith("_scale") and v == 0.0:
                raise InvalidInputError(f"RPC {self.source}: `{k}` must be non-zero; got {v!r}")
            object.__setattr__(self, k, v)
        for k in RPC_COEFFICIENTS:
            c = np.array(getattr(self, k), dtype=np.float64, copy=True).reshape(-1)
            if c.shape != (20,) or not np.isfinite(c).all():
                raise InvalidInputError(f"RPC {self.source}: `{k}` must be 20 finite numbers; got {c.size}")
            c.flags.writeable = False
            object.__setattr__(self, k, c)
        for k in ("line_den_coeff", "samp_den_coeff"):
            if not np.any(getattr(self, k)):
                raise InvalidInputError(f"RPC {self.source}: `{k}` is all zeros")

    # ------------------------------------------------------------ conversions
    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "RPC") -> RPC:
        """Build from rasterio's ``RPC.to_dict()`` keys (lower case, ``*_coeff`` lists)."""
        try:
            kw = {k: d[k] for k in RPC_SCALARS + RPC_COEFFICIENTS}
        except KeyError as err:
            raise InvalidInputError(f"RPC {source}: missing key {err.args[0]!r}") from None
        eb, er = d.get("err_bias"), d.get("err_rand")
        return cls(**kw, err_bias=None if eb is None else float(eb), err_rand=None if er is None else float(er),
                   source=source)

    def to_dict(self) -> dict[str, Any]:
        """rasterio's ``RPC(**d)`` keys."""
        d: dict[str, Any] = {k: getattr(self, k) for k in RPC_SCALARS}
        d.update({k: getattr(self, k).tolist() for k in RPC_COEFFICIENTS})
        d["err_bias"] = self.err_bias
        d["err_rand"] = self.err_rand
        return d

    def to_rasterio(self) -> dict[str, str]:
        """The model as GDAL's RPC metadata (``LINE_OFF``, ..., coefficient lists as space-separated text),
        the form ``rasterio.rpc.RPC.to_gdal`` gives: rasterio takes it as ``rpcs=`` when writing a raster and
        in ``RPCTransformer`` (for GDAL: its pixel frame is shifted by :data:`GDAL_PIXEL_OFFSET`)."""
        d = self.to_dict()
        out = {k.upper(): " ".join(map(str, d[k])) if k in RPC_COEFFICIENTS else str(d[k])
               for k in sorted(RPC_SCALARS + RPC_COEFFICIENTS)}
        for k in ("err_bias", "err_rand"):
            if d[k]:
                out[k.upper()] = str(d[k])
        return out

    def to_rpc_txt(self) -> str:
        """The model as an ``_RPC.TXT`` (IKONOS-style ``KEY: value``) text."""
        names = {"line_off": "LINE_OFF", "samp_off": "SAMP_OFF", "lat_off": "LAT_OFF", "long_off": "LONG_OFF",
                 "height_off": "HEIGHT_OFF", "line_scale": "LINE_SCALE", "samp_scale": "SAMP_SCALE",
                 "lat_scale": "LAT_SCALE", "long_scale": "LONG_SCALE", "height_scale": "HEIGHT_SCALE"}
        lines = [f"{v}: {float(getattr(self, k))!r}" for k, v in names.items()]
        for k in RPC_COEFFICIENTS:
            key = k.upper()
            lines += [f"{key}_{i + 1}: {float(c)!r}" for i, c in enumerate(getattr(self, k))]
        return "\n".join(lines) + "\n"

    # -------------------------------------------------------------- geometry
    @property
    def validity_box(self) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        """((lon_min, lon_max), (lat_min, lat_max), (h_min, h_max)): offset +- scale."""
        def rng(o: float, s: float) -> tuple[float, float]:
            return (o - abs(s), o + abs(s))
        return (rng(self.long_off, self.long_scale), rng(self.lat_off, self.lat_scale),
                rng(self.height_off, self.height_scale))

    def _normalise(self, g: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        return ((g[:, 0] - self.long_off) / self.long_scale, (g[:, 1] - self.lat_off) / self.lat_scale,
                (g[:, 2] - self.height_off) / self.height_scale)

    def project(self, ground: ArrayLike) -> NDArray[np.float64]:
        """Ground (N, 3) (lon deg, lat deg, h m above the ellipsoid) -> pixels (N, 2) (col, row).

        Raises
        ------
        ShapeError
            ``ground`` is not (N, 3).
        InvalidInputError
            A point is not finite or a denominator vanishes there (the message names the point).
        """
        g = _as_ground(ground)
        if not np.isfinite(g).all():
            i = int(np.flatnonzero(~np.isfinite(g).all(axis=1))[0])
            raise InvalidInputError(f"ground point {i} is not finite: {g[i].tolist()}")
        out = self._project(g)
        if not np.isfinite(out).all():
            i = int(np.flatnonzero(~np.isfinite(out).all(axis=1))[0])
            raise InvalidInputError(f"RPC {self.source}: denominator vanishes at ground point {g[i].tolist()}")
        return out

    def _project(self, g: NDArray) -> NDArray[np.float64]:
        L, P, H = self._normalise(g)
        m = _monomials(L, P, H)
        with np.errstate(divide="ignore", invalid="ignore"):
            samp = (m @ self.samp_num_coeff) / (m @ self.samp_den_coeff)
            line = (m @ self.line_num_coeff) / (m @ self.line_den_coeff)
        return np.column_stack([samp * self.samp_scale + self.samp_off, line * self.line_scale + self.line_off])

    def _jacobian(self, g: NDArray) -> NDArray[np.float64]:
        """d(col, row)/d(lon, lat), (N, 2, 2)."""
        L, P, H = self._normalise(g)
        m = _monomials(L, P, H)
        dL, dP = _d_monomials(L, P, H)
        J = np.empty((len(g), 2, 2))
        for i, (num, den, sc) in enumerate(((self.samp_num_coeff, self.samp_den_coeff, self.samp_scale),
                                            (self.line_num_coeff, self.line_den_coeff, self.line_scale))):
            n, d = m @ num, m @ den
            for j, (dm, gs) in enumerate(((dL, self.long_scale), (dP, self.lat_scale))):
                J[:, i, j] = sc * ((dm @ num) * d - n * (dm @ den)) / (d * d) / gs
        return J

    def localize(self, pixels: ArrayLike, heights: ArrayLike, *, tol_px: float = 1e-9,
                 max_iter: int = 50, on_failure: str = "raise") -> NDArray[np.float64]:
        """Image -> ground at given heights: (lon, lat, h) (N, 3) with ``project`` = ``pixels``.

        Newton's method on (lon, lat) with the analytic Jacobian, started from
        an affine approximation of the inverse fitted over the validity box at
        each height, so it converges anywhere in the image (and a little
        beyond). Stops when the projection is within ``tol_px`` of the pixel.

        Parameters
        ----------
        pixels : (N, 2) float64 (col, row)
        heights : float or (N,) float64, metres above the ellipsoid
        on_failure : ``"raise"`` or ``"nan"``
            What to do with points that do not converge.

        Raises
        ------
        ConvergenceError
            A point did not converge (the message names the first pixel and height).
        """
        p = _as_pixels(pixels)
        h = np.broadcast_to(np.asarray(heights, dtype=np.float64), (len(p),)).copy() if np.ndim(heights) == 0 \
            else np.asarray(heights, dtype=np.float64).reshape(-1)
        if h.shape != (len(p),):
            raise ShapeError(f"`heights` must be a number or ({len(p)},); got shape {np.shape(heights)}",
                             actual_shape=np.shape(heights), expected_shape=(len(p),))
        if on_failure not in ("raise", "nan"):
            raise InvalidInputError(f"on_failure must be 'raise' or 'nan'; got {on_failure!r}")
        bad = ~(np.isfinite(p).all(axis=1) & np.isfinite(h))
        if bad.any() and on_failure == "raise":
            i = int(np.flatnonzero(bad)[0])
            raise InvalidInputError(f"pixel {i} or its height is not finite: {p[i].tolist()}, {h[i]!r}")
        g = np.column_stack([self._initial_guess(p, h), h])
        done = bad.copy()
        it = 0
        while it < max_iter:
            act = ~done
            if not act.any():
                break
            it += 1
            ga = g[act]
            r = p[act] - self._project(ga)
            J = self._jacobian(ga)
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                dlon = (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
                dlat = (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
            # damp steps larger than the validity box (far-off starts)
            lim_lon, lim_lat = 0.5 * abs(self.long_scale), 0.5 * abs(self.lat_scale)
            dlon = np.clip(dlon, -lim_lon, lim_lon)
            dlat = np.clip(dlat, -lim_lat, lim_lat)
            ga[:, 0] += dlon
            ga[:, 1] += dlat
            g[act] = ga
            with np.errstate(invalid="ignore"):
                step_px = np.hypot(J[:, 0, 0] * dlon + J[:, 0, 1] * dlat, J[:, 1, 0] * dlon + J[:, 1, 1] * dlat)
                ok = (np.abs(r).max(axis=1) < tol_px) | (step_px < tol_px)
            stuck = ~np.isfinite(ga).all(axis=1)
            idx = np.flatnonzero(act)
            done[idx[ok | stuck]] = True
            g[idx[stuck]] = np.nan
        res = np.full(len(p), np.inf)
        fin = np.isfinite(g).all(axis=1)
        res[fin] = np.abs(p[fin] - self._project(g[fin])).max(axis=1)
        fail = ~bad & ~(res < max(10 * tol_px, 1e-6))
        if fail.any():
            if on_failure == "raise":
                i = int(np.flatnonzero(fail)[0])
                raise ConvergenceError(
                    f"RPC {self.source}: localisation of pixel {p[i].tolist()} at height {h[i]:.3f} m did not "
                    f"converge (residual {res[i]:.3g} px after {it} iterations); {int(fail.sum())} point(s) "
                    f"failed: is the pixel far outside the image or the height far outside "
                    f"{self.validity_box[2]}?", iterations=it)
            g[fail] = np.nan
        g[bad] = np.nan
        g[:, 2] = h
        return g

    def _initial_guess(self, p: NDArray, h: NDArray) -> NDArray[np.float64]:
        """Affine inverse (col, row, h) -> (lon, lat) fitted on a 5x5x3 grid of the validity box."""
        (x0, x1), (y0, y1), (z0, z1) = self.validity_box
        lo, la, hh = np.meshgrid(np.linspace(x0, x1, 5), np.linspace(y0, y1, 5), np.linspace(z0, z1, 3))
        g = np.column_stack([lo.ravel(), la.ravel(), hh.ravel()])
        px = self._project(g)
        ok = np.isfinite(px).all(axis=1)
        A = np.column_stack([px[ok], g[ok, 2], np.ones(ok.sum())])
        coef, *_ = np.linalg.lstsq(A, g[ok, :2], rcond=None)
        hc = np.where(np.isfinite(h), h, self.height_off)
        pc = np.where(np.isfinite(p), p, 0.0)
        return np.column_stack([pc, hc, np.ones(len(p))]) @ coef

    def localize_on_dem(self, pixels: ArrayLike, dem: Callable[[NDArray], NDArray], *,
                        h_range: tuple[float, float] | None = None, tol_m: float = 1e-4,
                        on_failure: str = "raise", n_scan: int = 128) -> NDArray[np.float64]:
        """Image -> the first ground point of a DEM along the line of sight, (N, 3).

        The line of sight is scanned from the top of ``h_range`` down in
        ``n_scan`` steps (so the *visible* surface is found, not a hidden one;
        features thinner than a step along the line may be missed); the first bracket where
        ``h - dem(lon, lat)`` changes sign is refined by the secant/bisection
        method on exact localisations until the height is within ``tol_m``.

        Parameters
        ----------
        pixels : (N, 2) (col, row)
        dem : callable (M, 2) (lon, lat) -> (M,) ellipsoidal heights (NaN outside)
        h_range : (h_min, h_max), optional
            Heights to scan; default the RPC's height validity range.

        Raises
        ------
        ConvergenceError
            The line of sight of a pixel does not meet the DEM within ``h_range``
            (the message names the pixel).
        """
        p = _as_pixels(pixels)
        lo, hi = h_range if h_range is not None else self.validity_box[2]
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise InvalidInputError(f"h_range must be two finite heights, low < high; got {h_range!r}")
        if on_failure not in ("raise", "nan"):
            raise InvalidInputError(f"on_failure must be 'raise' or 'nan'; got {on_failure!r}")
        n = len(p)
        # the line of sight between the top and the bottom of h_range; it is straight to well under a
        # millimetre over a DEM's height range, so the scan interpolates it and only the root is exact
        top = self.localize(p, hi, on_failure="nan")
        bot = self.localize(p, lo, on_failure="nan")
        steps = n_scan
        a_h, b_h = np.full(n, np.nan), np.full(n, np.nan)
        found = np.zeros(n, bool)
        prev_f = np.full(n, np.nan)
        active = np.isfinite(top).all(axis=1) & np.isfinite(bot).all(axis=1)
        for k in range(steps + 1):
            idx = np.flatnonzero(active & ~found)
            if not len(idx):
                break
            t = k / steps
            gi = top[idx] * (1 - t) + bot[idx] * t
            fi = gi[:, 2] - _dem_eval(dem, gi[:, :2])
            below = fi <= 0
            first = below & (k == 0)
            hit = below & ~first & np.isfinite(prev_f[idx])
            a_h[idx[hit]] = hi + (lo - hi) * (k - 1) / steps
            b_h[idx[hit]] = gi[hit, 2]
            a_h[idx[first]] = b_h[idx[first]] = hi  # below the surface at the top of h_range
            found[idx[hit | first]] = True
            prev_f[idx] = np.where(np.isfinite(fi), fi, prev_f[idx])
        if not found.all() and on_failure == "raise":
            i = int(np.flatnonzero(~found)[0])
            raise ConvergenceError(f"RPC {self.source}: the line of sight of pixel {p[i].tolist()} does not meet "
                                   f"the DEM between {lo:.1f} and {hi:.1f} m (outside the DEM or h_range?)")
        out = np.full((n, 3), np.nan)
        idx = np.flatnonzero(found)
        if len(idx):
            a, b = a_h[idx], b_h[idx]
            pp = p[idx]
            fa = a - _dem_eval(dem, self.localize(pp, a, on_failure="nan")[:, :2])
            fb = b - _dem_eval(dem, self.localize(pp, b, on_failure="nan")[:, :2])
            best_h = np.where(np.abs(fa) < np.abs(fb), a, b)
            best_f = np.minimum(np.abs(fa), np.abs(fb))
            last = np.zeros(len(idx), np.int8)  # Illinois variant of regula falsi: +1 a moved, -1 b moved
            act = np.ones(len(idx), bool)
            for _ in range(60):
                j = np.flatnonzero(act)
                if not len(j):
                    break
                aj, bj, faj, fbj = a[j], b[j], fa[j], fb[j]
                with np.errstate(divide="ignore", invalid="ignore"):
                    m = np.where(np.abs(faj - fbj) > 1e-12, bj - fbj * (bj - aj) / (fbj - faj), 0.5 * (aj + bj))
                m = np.where((m > np.minimum(aj, bj)) & (m < np.maximum(aj, bj)), m, 0.5 * (aj + bj))
                gm = self.localize(pp[j], m, on_failure="nan")
                fm = m - _dem_eval(dem, gm[:, :2])
                # keep the bracket: a above the surface (f > 0), b below (f <= 0)
                above = fm > 0
                fb[j] = np.where(above & (last[j] == 1), 0.5 * fbj, fbj)
                fa[j] = np.where(~above & (last[j] == -1), 0.5 * faj, faj)
                a[j] = np.where(above, m, aj)
                fa[j] = np.where(above, fm, fa[j])
                b[j] = np.where(above, bj, m)
                fb[j] = np.where(above, fb[j], fm)
                last[j] = np.where(above, 1, -1)
                better = np.abs(fm) < best_f[j]
                best_h[j[better]] = m[better]
                best_f[j[better]] = np.abs(fm[better])
                act[j] = ~((np.abs(fm) < tol_m) | ~np.isfinite(fm) | (np.abs(a[j] - b[j]) < tol_m * 1e-3))
            out[idx] = self.localize(pp, best_h, on_failure="nan")
        return out

    # ------------------------------------------------------------ synthetic
    @classmethod
    def from_coefficients(cls, *, offsets: Sequence[float], scales: Sequence[float],
                          samp_num: ArrayLike, samp_den: ArrayLike | None = None, line_num: ArrayLike,
                          line_den: ArrayLike | None = None, source: str = "synthetic RPC") -> RPC:
        """Build from (line, samp, lat, lon, h) offsets and scales and coefficient vectors (padded to 20)."""
        def pad(c: ArrayLike | None, first: float) -> NDArray[np.float64]:
            v = np.zeros(20)
            if c is None:
                v[0] = first
            else:
                a = np.asarray(c, dtype=np.float64).reshape(-1)
                if a.size > 20:
                    raise InvalidInputError(f"at most 20 RPC coefficients; got {a.size}")
                v[:a.size] = a
            return v
        if len(offsets) != 5 or len(scales) != 5:
            raise InvalidInputError(f"offsets and scales must be 5 numbers (line, samp, lat, lon, h); "
                                    f"got {len(offsets)} and {len(scales)}")
        lo, so, lao, loo, ho = offsets
        ls, ss, las, los, hs = scales
        return cls(lo, so, lao, loo, ho, ls, ss, las, los, hs, pad(line_num, 0), pad(line_den, 1),
                   pad(samp_num, 0), pad(samp_den, 1), source=source)


def _dem_eval(dem: Callable[[NDArray], NDArray], lonlat: NDArray) -> NDArray[np.float64]:
    out = np.full(len(lonlat), np.nan)
    ok = np.isfinite(lonlat).all(axis=1)
    if ok.any():
        out[ok] = np.asarray(dem(lonlat[ok]), dtype=np.float64).reshape(-1)
    return out


def fit_rpc(project: Callable[[NDArray], NDArray], box: tuple[tuple[float, float], ...], *,
            n_xy: int = 15, n_h: int = 7, source: str = "fitted RPC") -> RPC:
    """Fit a terrain-independent RPC to a physical model (ground (N,3) -> pixels (N,2)).

    The standard linearised least squares over an ``n_xy`` x ``n_xy`` x ``n_h``
    grid of the box ((lon0, lon1), (lat0, lat1), (h0, h1)); used to build
    synthetic RPC images from a frame or pushbroom geometry in tests.
    """
    (x0, x1), (y0, y1), (z0, z1) = box
    lo, la, hh = np.meshgrid(np.linspace(x0, x1, n_xy), np.linspace(y0, y1, n_xy), np.linspace(z0, z1, n_h))
    g = np.column_stack([lo.ravel(), la.ravel(), hh.ravel()])
    px = np.asarray(project(g), dtype=np.float64)
    if px.shape != (len(g), 2) or not np.isfinite(px).all():
        raise EstimationError("the physical model does not project the fitting grid to finite pixels")
    offs = [0.5 * (px[:, 1].min() + px[:, 1].max()), 0.5 * (px[:, 0].min() + px[:, 0].max()),
            0.5 * (y0 + y1), 0.5 * (x0 + x1), 0.5 * (z0 + z1)]
    scs = [max(0.5 * (px[:, 1].max() - px[:, 1].min()), 1.0), max(0.5 * (px[:, 0].max() - px[:, 0].min()), 1.0),
           0.5 * (y1 - y0), 0.5 * (x1 - x0), 0.5 * (z1 - z0)]
    L = (g[:, 0] - offs[3]) / scs[3]
    P = (g[:, 1] - offs[2]) / scs[2]
    H = (g[:, 2] - offs[4]) / scs[4]
    m = _monomials(L, P, H)
    coefs = []
    for k, (o, s) in enumerate(((offs[1], scs[1]), (offs[0], scs[0]))):
        y = (px[:, k] - o) / s
        A = np.hstack([m, -y[:, None] * m[:, 1:]])
        sol, *_ = np.linalg.lstsq(A, y, rcond=None)
        coefs.append((sol[:20], np.concatenate([[1.0], sol[20:]])))
    (sn, sd), (ln, ld) = coefs
    return RPC.from_coefficients(offsets=offs, scales=scs, samp_num=sn, samp_den=sd, line_num=ln, line_den=ld,
                                 source=source)


# =========================================================================== refinement
REFINEMENT_MODELS = {"shift": 1, "drift": 2, "affine": 3}


def _design(px: NDArray, model: str) -> NDArray[np.float64]:
    """Columns of the bias model evaluated at projected pixels (N, k) for each image axis."""
    one = np.ones(len(px))
    if model == "shift":
        return one[:, None]
    if model == "drift":
        return np.column_stack([one, px[:, 1]])
    return np.column_stack([one, px[:, 0], px[:, 1]])


@dataclass(frozen=True, eq=False)
class RPCRefinement:
    """An RPC with an image-space bias compensation fitted to GCPs.

    ``col' = col + dc(col, row)``, ``row' = row + dr(col, row)``, where the
    corrections are (with (col, row) the plain RPC projection):

    - ``shift``: dc = a0, dr = b0 (2 parameters, 1 GCP minimum);
    - ``drift``: dc = a0 + a1 row, dr = b0 + b1 row (shift + drift along the
      scan direction, time; 4 parameters, 2 GCPs);
    - ``affine``: dc = a0 + a1 col + a2 row, dr = b0 + b1 col + b2 row (6, 3 GCPs).

    Attributes
    ----------
    rpc : RPC
    model : str
    params : (2, k) float64
        Correction coefficients for col (row 0) and row (row 1).
    residuals : ResidualTable or None
        Image residuals (px) at the GCPs; check points carry leave-one-out
        style errors (they were never in the fit); ``extra["loo_rmse_px"]``
        is the leave-one-out RMSE over the fit points.
    loo_errors : (M, 2) float64 or None
        Leave-one-out errors at the fit points (px).
    """

    rpc: RPC
    model: str = "shift"
    params: NDArray[np.float64] = field(default_factory=lambda: np.zeros((2, 1)))
    residuals: Any = None
    loo_errors: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        if self.model not in REFINEMENT_MODELS:
            raise InvalidInputError(f"unknown refinement model {self.model!r}; expected one of "
                                    f"{list(REFINEMENT_MODELS)}")
        p = np.array(self.params, dtype=np.float64, copy=True)
        if p.shape != (2, REFINEMENT_MODELS[self.model]) or not np.isfinite(p).all():
            raise ShapeError(f"refinement params for {self.model!r} must be finite (2, "
                             f"{REFINEMENT_MODELS[self.model]}); got shape {p.shape}")
        p.flags.writeable = False
        object.__setattr__(self, "params", p)

    @classmethod
    def from_gcps(cls, rpc: RPC, pixels: ArrayLike, ground: ArrayLike, *, model: str = "shift",
                  ids: Sequence[str] | None = None, check: ArrayLike | None = None) -> RPCRefinement:
        """Fit the bias model to GCPs (pixels (N, 2), ground (N, 3) lon/lat/ellipsoidal h).

        Check points (``check`` True) are not used in the fit; their errors
        are reported. The leave-one-out error of each fit point is its error
        when the model is refitted without it.

        Raises
        ------
        EstimationError
            Fewer fit points than the model needs, or a degenerate configuration.
        """
        if model not in REFINEMENT_MODELS:
            raise InvalidInputError(f"unknown refinement model {model!r}; expected one of {list(REFINEMENT_MODELS)}")
        pix = _as_pixels(pixels)
        g = _as_ground(ground)
        if len(pix) != len(g):
            raise ShapeError(f"pixels ({len(pix)}) and ground ({len(g)}) must have the same length",
                             actual_shape=g.shape, expected_shape=(len(pix), 3))
        if not (np.isfinite(pix).all() and np.isfinite(g).all()):
            raise InvalidInputError("GCP pixels and ground coordinates must be finite")
        chk = np.zeros(len(pix), bool) if check is None else np.asarray(check, dtype=bool).reshape(-1)
        if chk.shape != (len(pix),):
            raise ShapeError(f"`check` must have shape ({len(pix)},); got {chk.shape}")
        names = [str(i + 1) for i in range(len(pix))] if ids is None else [str(i) for i in ids]
        k = REFINEMENT_MODELS[model]
        fit = ~chk
        if fit.sum() < k:
            raise EstimationError(f"refinement {model!r} needs at least {k} GCPs; got {int(fit.sum())}")
        proj = rpc.project(g)
        d = pix - proj

        def solve(mask: NDArray[np.bool_]) -> NDArray[np.float64]:
            A = _design(proj[mask], model)
            if np.linalg.matrix_rank(A) < k:
                raise EstimationError(f"refinement {model!r}: GCPs are degenerate (collinear or coincident) for "
                                      f"the {k}-parameter model; use 'shift' or spread the GCPs")
            sol, *_ = np.linalg.lstsq(A, d[mask], rcond=None)
            return sol.T

        params = solve(fit)
        adj = proj + _design(proj, model) @ params.T
        loo = np.full((len(pix), 2), np.nan)
        fit_idx = np.flatnonzero(fit)
        if len(fit_idx) > k:
            for i in fit_idx:
                m = fit.copy()
                m[i] = False
                try:
                    pi = solve(m)
                except EstimationError:
                    continue
                loo[i] = proj[i] + _design(proj[i:i + 1], model)[0] @ pi.T - pix[i]
        loo_fit = loo[fit_idx]
        loo_ok = np.isfinite(loo_fit).all(axis=1)
        table = ResidualTable(
            step=f"RPC refinement ({model})", ids=names, observed=pix, adjusted=adj, units="px",
            check=chk, position_px=pix, n_params=2 * k,
            extra={"model": model, "loo_rmse_px": rms(np.hypot(*loo_fit[loo_ok].T)) if loo_ok.any() else None,
                   "rpc_only_rmse_px": rms(np.hypot(*d[fit].T))})
        logger.info("RPC refinement %s on %d GCPs: params %s", model, int(fit.sum()), params.tolist())
        return cls(rpc, model, params, table, loo_fit)

    @property
    def source(self) -> str:
        return self.rpc.source

    @property
    def validity_box(self):
        return self.rpc.validity_box

    def correction(self, px: NDArray) -> NDArray[np.float64]:
        """Bias (dc, dr) at RPC pixels (N, 2)."""
        return _design(px, self.model) @ self.params.T

    def project(self, ground: ArrayLike) -> NDArray[np.float64]:
        """Ground (N, 3) -> corrected pixels (N, 2)."""
        px = self.rpc.project(ground)
        return px + self.correction(px)

    def _project(self, g: NDArray) -> NDArray[np.float64]:
        px = self.rpc._project(g)
        return px + self.correction(px)

    def uncorrect(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Corrected pixels -> plain RPC pixels (the inverse of the bias model; exact, it is affine)."""
        p = _as_pixels(pixels)
        one = np.ones(len(p))
        if self.model == "shift":
            return p - self.params[:, 0]
        a, b = self.params
        if self.model == "drift":
            # c' = c + a0 + a1 r; r' = r + b0 + b1 r
            r = (p[:, 1] - b[0]) / (1.0 + b[1])
            return np.column_stack([p[:, 0] - a[0] - a[1] * r, r])
        M = np.array([[1.0 + a[1], a[2]], [b[1], 1.0 + b[2]]])
        rhs = p - np.column_stack([a[0] * one, b[0] * one])
        return np.linalg.solve(M, rhs.T).T

    def localize(self, pixels: ArrayLike, heights: ArrayLike, **kw) -> NDArray[np.float64]:
        return self.rpc.localize(self.uncorrect(pixels), heights, **kw)

    def localize_on_dem(self, pixels: ArrayLike, dem: Callable[[NDArray], NDArray], **kw) -> NDArray[np.float64]:
        return self.rpc.localize_on_dem(self.uncorrect(pixels), dem, **kw)
