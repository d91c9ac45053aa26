"""A GNSS/INS trajectory interpolated to the exposure times of the images.

A trajectory is a time series of antenna positions and navigation angles (heading, pitch, roll;
:mod:`stereo.block.navigation`) sampled by the navigation system, usually at 10-200 Hz; an image's
pose is the trajectory at its exposure time (seed 002, section 3.3.3: the GNSS receiver gives
positions at its own epochs "and, by interpolation, at the moment of exposure").

Interpolation
-------------
positions
    ``"cubic"`` (default): the not-a-knot cubic spline through the samples
    (:class:`scipy.interpolate.CubicSpline`), which reproduces a trajectory that is a cubic
    polynomial of time exactly; ``"linear"``: piecewise linear, exact for a straight line flown at a
    constant speed. With fewer than four samples the cubic spline is replaced by the linear one.
attitude
    Spherical linear interpolation (SLERP) of the body rotations (body -> ground, built from
    heading, pitch and roll by :func:`stereo.block.navigation.body_rotation`) between the two
    samples around the time: the rotation about the one axis that takes one sample into the next,
    at a constant rate. It works on rotations, not on angles, so a heading that passes north
    (359 deg -> 1 deg) interpolates through 0, never through 180.
standard deviations
    Interpolated linearly (each column), when the trajectory has them.

A time outside the trajectory's span is an error naming the image, its time and the span (no
extrapolation).

Units: times in seconds (any epoch, the same in the trajectory and the image times), positions
in metres of the ground frame, angles in radians.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.rotation import angles_from_matrix
from stereo.block.navigation import body_rotation, check_convention, navigation_from_rotation, rotation_from_navigation

__all__ = ["INTERPOLATIONS", "Trajectory", "TrajectorySample", "opk_covariance", "slerp"]

F64 = NDArray[np.float64]

#: position interpolation methods of :meth:`Trajectory.sample`
INTERPOLATIONS: tuple[str, ...] = ("cubic", "linear")


@dataclass(frozen=True, eq=False)
class TrajectorySample:
    """The trajectory at n exposure times.

    Attributes
    ----------
    time : (n,) float64
        The times, s.
    position : (n, 3) float64
        Antenna positions, ground frame, m.
    body_rotation : (n, 3, 3) float64
        Body (x right wing, y forward, z up) -> ground (east, north, up) rotations.
    navigation : (n, 3) float64
        Heading, pitch, roll of ``body_rotation``, rad (heading in [0, 2 pi)).
    sigma : (n, 6) float64 or None
        Standard deviations of x, y, z (m) and heading, pitch, roll (rad); NaN where the trajectory
        has none.
    """

    time: F64
    position: F64
    body_rotation: F64
    navigation: F64
    sigma: F64 | None


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Navigation samples: times, antenna positions, heading/pitch/roll and their standard deviations.

    Parameters
    ----------
    time : (m,) array_like
        Sample times, s; strictly increasing, at least two.
    position : (m, 3) array_like
        Antenna positions, ground frame, m.
    navigation : (m, 3) array_like
        Heading, pitch, roll, rad (:mod:`stereo.block.navigation`).
    sigma : (m, 6) array_like, optional
        Standard deviations of x, y, z (m) and heading, pitch, roll (rad); NaN where unknown, else > 0.
    convention : {"seed004", "euler"}
        Roll definition (:func:`stereo.block.navigation.rotation_from_navigation`).
    source : str
        What the samples came from (a file name), for error messages.

    Raises
    ------
    ShapeError, InvalidInputError
        Shapes, non-finite values, fewer than two samples, times not strictly increasing (the first
        offending pair named), negative or zero standard deviations, angles with no orthogonal axes.
    """

    time: F64
    position: F64
    navigation: F64
    sigma: F64 | None = None
    convention: str = "seed004"
    source: str = "trajectory"

    def __post_init__(self) -> None:
        t = np.array(self.time, dtype=np.float64, copy=True).reshape(-1)
        m = len(t)
        pos = np.array(self.position, dtype=np.float64, copy=True)
        nav = np.array(self.navigation, dtype=np.float64, copy=True)
        if m < 2:
            raise InvalidInputError(f"{self.source}: a trajectory needs at least 2 samples; got {m}")
        for name, a in (("position", pos), ("navigation", nav)):
            if a.shape != (m, 3):
                raise ShapeError(f"{self.source}: `{name}` must have shape ({m}, 3); got {a.shape}",
                                 actual_shape=a.shape, expected_shape=(m, 3))
        for name, a in (("time", t), ("position", pos), ("navigation", nav)):
            bad = np.flatnonzero(~np.isfinite(a.reshape(m, -1)).all(axis=1))
            if len(bad):
                raise InvalidInputError(f"{self.source}: sample {int(bad[0])} has a non-finite {name} "
                                        f"{a[int(bad[0])].tolist()!r}")
        dt = np.diff(t)
        if (dt <= 0).any():
            k = int(np.flatnonzero(dt <= 0)[0])
            raise InvalidInputError(f"{self.source}: times must increase strictly; sample {k + 1} at "
                                    f"{float(t[k + 1])!r} s follows {float(t[k])!r} s")
        sig = None
        if self.sigma is not None:
            sig = np.array(self.sigma, dtype=np.float64, copy=True)
            if sig.shape != (m, 6):
                raise ShapeError(f"{self.source}: `sigma` must have shape ({m}, 6); got {sig.shape}",
                                 actual_shape=sig.shape, expected_shape=(m, 6))
            with np.errstate(invalid="ignore"):
                bad = np.flatnonzero((sig <= 0).any(axis=1) | np.isinf(sig).any(axis=1))
            if len(bad):
                raise InvalidInputError(f"{self.source}: sample {int(bad[0])} has a standard deviation that is not "
                                        f"finite and > 0: {sig[int(bad[0])].tolist()!r}")
        conv = check_convention(self.convention)
        body_rotation(nav[:, 0], nav[:, 1], nav[:, 2], convention=conv)  # the angles admit axes
        for arr in (t, pos, nav, sig):
            if arr is not None:
                arr.flags.writeable = False
        object.__setattr__(self, "time", t)
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "navigation", nav)
        object.__setattr__(self, "sigma", sig)

    @property
    def span(self) -> tuple[float, float]:
        """(first, last) sample time, s."""
        return float(self.time[0]), float(self.time[-1])

    def check_covers(self, times: ArrayLike, names: Sequence[str] | None = None) -> F64:
        """``times`` (n,) as float64 if every one is finite and inside :attr:`span`; else the error names the
        first image outside (``names``, else its index), its time and the span."""
        tq = np.asarray(times, dtype=np.float64).reshape(-1)
        t0, t1 = self.span
        with np.errstate(invalid="ignore"):
            out = np.flatnonzero(~((tq >= t0) & (tq <= t1)))
        if len(out):
            i = int(out[0])
            who = f"image {names[i]!r}" if names is not None and i < len(names) else f"time index {i}"
            more = f" ({len(out)} images in all)" if len(out) > 1 else ""
            raise InvalidInputError(f"{who}: exposure time {float(tq[i])!r} s is outside the {self.source} span "
                                    f"{t0!r} .. {t1!r} s{more}")
        return tq

    def sample(self, times: ArrayLike, *, names: Sequence[str] | None = None,
               interpolation: str = "cubic") -> TrajectorySample:
        """The trajectory at ``times`` (n,), s.

        Parameters
        ----------
        times : (n,) array_like
            Exposure times, s, inside :attr:`span`.
        names : sequence of str, optional
            The images' names, for the error of a time outside the span.
        interpolation : {"cubic", "linear"}
            Position interpolation (see the module docstring); the attitude is always SLERP.

        Returns
        -------
        TrajectorySample

        Raises
        ------
        InvalidInputError
            An unknown interpolation, a time outside the span or not finite.
        """
        if interpolation not in INTERPOLATIONS:
            raise InvalidInputError(f"unknown trajectory interpolation {interpolation!r}; expected one of "
                                    f"{list(INTERPOLATIONS)}")
        tq = self.check_covers(times, names)
        t = self.time
        if interpolation == "cubic" and len(t) >= 4:
            pos = np.asarray(CubicSpline(t, self.position, axis=0)(tq), dtype=np.float64).reshape(-1, 3)
        else:
            pos = np.column_stack([np.interp(tq, t, self.position[:, k]) for k in range(3)])
        Rb = body_rotation(self.navigation[:, 0], self.navigation[:, 1], self.navigation[:, 2],
                           convention=self.convention)
        Rq = slerp(t, Rb, tq)
        nav = navigation_from_rotation(Rq, convention=self.convention)
        sig = None
        if self.sigma is not None:
            sig = np.column_stack([np.interp(tq, t, self.sigma[:, k]) for k in range(6)])
        return TrajectorySample(tq.copy(), pos, Rq, nav, sig)


def slerp(t: F64, R: F64, tq: F64) -> F64:
    """Rotations (n, 3, 3) at times ``tq`` (n,) by spherical linear interpolation between the samples
    ``R`` (m, 3, 3) at the increasing times ``t`` (m,); ``tq`` inside [t[0], t[-1]]."""
    k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    u = (tq - t[k]) / (t[k + 1] - t[k])
    r0 = Rotation.from_matrix(R[k])
    rel = (r0.inv() * Rotation.from_matrix(R[k + 1])).as_rotvec()   # body-frame step from sample k to k + 1
    out = r0 * Rotation.from_rotvec(rel * u[:, None])
    return np.asarray(out.as_matrix(), dtype=np.float64).reshape(-1, 3, 3)


def opk_covariance(R: ArrayLike, cov_nav: ArrayLike, *, boresight_rad: ArrayLike | None = None,
                   convention: str = "seed004", step: float = 1e-6) -> F64:
    """Covariances of (x, y, z, omega, phi, kappa) from those of (x, y, z, heading, pitch, roll).

    Parameters
    ----------
    R : (n, 3, 3)
        Camera rotations (photo -> ground) built from the navigation angles with ``boresight_rad``.
    cov_nav : (n, 6, 6)
        Covariances of position (m) and heading, pitch, roll (rad).

    Returns
    -------
    (n, 6, 6) float64
        ``T K T^T`` with ``T = diag(I, d(omega, phi, kappa) / d(heading, pitch, roll))``, the Jacobian
        by central differences of ``step`` rad.
    """
    Rm = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    K = np.asarray(cov_nav, dtype=np.float64).reshape(-1, 6, 6)
    nav = navigation_from_rotation(Rm, boresight_rad=boresight_rad, convention=convention)
    T = np.zeros((len(Rm), 6, 6))
    T[:, :3, :3] = np.eye(3)
    for k in range(3):
        d = np.zeros(3)
        d[k] = step
        a = [np.asarray(angles_from_matrix(rotation_from_navigation(*(nav + sgn * d).T, boresight_rad=boresight_rad,
                                                                    convention=convention), "omega-phi-kappa"),
                        dtype=np.float64).reshape(-1, 3) for sgn in (1.0, -1.0)]
        diff = a[0] - a[1]
        diff = -((-diff + np.pi) % (2 * np.pi) - np.pi)
        T[:, 3:, 3 + k] = diff / (2 * step)
    return np.asarray(T @ K @ np.transpose(T, (0, 2, 1)), dtype=np.float64)
