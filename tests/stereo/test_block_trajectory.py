"""GNSS/INS trajectories interpolated to the exposure times (stereo.block.trajectory,
stereo.formats.trajectory), pose-file times, strips and correlations, ``stereo block --trajectory``."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.rotation import angles_from_matrix
from stereo.actions.block import BlockOptions, run_block
from stereo.block.bundle.adjust import BundleOptions
from stereo.block.navigation import body_rotation, navigation_from_rotation
from stereo.block.trajectory import Trajectory, opk_covariance
from stereo.block.types import GnssObservations
from stereo.cli.main import cli
from stereo.formats.block import read_block_orientation
from stereo.formats.poses import read_pose_csv
from stereo.formats.trajectory import gnss_with_extras, read_pose_extras, read_trajectory_csv
from tests.support.block_files import write_block_files
from tests.support.block_synthetic import make_block


def _level(m: int, heading_deg: np.ndarray | float = 0.0) -> np.ndarray:
    return np.column_stack([np.radians(np.broadcast_to(heading_deg, (m,))), np.zeros(m), np.zeros(m)])


# ---------------------------------------------------------------------------- interpolation closed forms
def test_linear_and_cubic_trajectories_are_reproduced():
    t = np.array([0.0, 1.0, 2.5, 3.0, 4.5, 6.0])
    tq = np.array([0.0, 0.3, 1.7, 2.9, 5.99, 6.0])
    lin = lambda x: np.column_stack([100 + 50 * x, -3 * x, 1000 + 0.5 * x])  # noqa: E731
    cub = lambda x: np.column_stack([1 + 2 * x - x ** 2 + 0.3 * x ** 3, 5 - x ** 3, 0.1 * x ** 2])  # noqa: E731
    tr = Trajectory(t, lin(t), _level(len(t)))
    np.testing.assert_allclose(tr.sample(tq, interpolation="linear").position, lin(tq), atol=1e-10)
    np.testing.assert_allclose(tr.sample(tq).position, lin(tq), atol=1e-10)  # a line is a cubic too
    tc = Trajectory(t, cub(t), _level(len(t)))
    np.testing.assert_allclose(tc.sample(tq).position, cub(tq), atol=1e-10)
    # the linear interpolation of a cubic is not exact: the cubic one is what reproduces it
    assert np.abs(tc.sample(tq, interpolation="linear").position - cub(tq)).max() > 0.01


def test_slerp_across_north():
    """Heading 359 deg -> 1 deg: halfway the heading is 0 (not 180), a quarter of the way 359.5 deg."""
    tr = Trajectory([0.0, 1.0], np.zeros((2, 3)), _level(2, np.array([359.0, 1.0])))
    s = tr.sample([0.25, 0.5, 0.75])
    h = np.degrees(s.navigation[:, 0])
    np.testing.assert_allclose(np.mod(h + 180.0, 360.0) - 180.0, [-0.5, 0.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(s.navigation[:, 1:], 0.0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(h0=st.floats(0.0, 360.0), rate=st.floats(-20.0, 20.0), pitch=st.floats(-5.0, 5.0),
       u=st.floats(0.0, 1.0))
def test_slerp_reproduces_a_constant_rate_turn(h0, rate, pitch, u):
    """A turn at a constant rate about the vertical (pitch and roll held) is a rotation about one axis at a constant
    rate: SLERP between samples 1 s apart gives it exactly at any time between them."""
    t = np.arange(4.0)
    nav = np.column_stack([np.radians(h0 + rate * t), np.full(4, np.radians(pitch)), np.zeros(4)])
    tr = Trajectory(t, np.zeros((4, 3)), nav, convention="euler")
    tq = np.array([1.0 + u])
    got = tr.sample(tq).body_rotation[0]
    want = body_rotation(np.radians(h0 + rate * tq[0]), np.radians(pitch), 0.0, convention="euler")
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_samples_are_exact_at_the_sample_times():
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.1, 1.0, 8))
    nav = np.column_stack([rng.uniform(0, 2 * np.pi, 8), rng.normal(0, 0.05, 8), rng.normal(0, 0.05, 8)])
    pos = rng.normal(0, 100, (8, 3))
    s = Trajectory(t, pos, nav).sample(t)
    np.testing.assert_allclose(s.position, pos, atol=1e-9)
    np.testing.assert_allclose(s.body_rotation, body_rotation(nav[:, 0], nav[:, 1], nav[:, 2]), atol=1e-12)


def test_time_outside_the_span_names_image_time_and_span():
    tr = Trajectory([10.0, 20.0], np.zeros((2, 3)), _level(2))
    with pytest.raises(InvalidInputError, match=r"image 'b.tif': exposure time 20.5 s is outside the trajectory "
                                                r"span 10.0 .. 20.0 s \(2 images in all\)"):
        tr.sample([15.0, 20.5, 9.0], names=["a.tif", "b.tif", "c.tif"])
    with pytest.raises(InvalidInputError, match="unknown trajectory interpolation 'spline'"):
        tr.sample([15.0], interpolation="spline")


@pytest.mark.parametrize("case,match", [
    ("order", "times must increase strictly; sample 2 at 1.0 s follows 2.0 s"),
    ("one", "at least 2 samples"),
    ("nan", "sample 1 has a non-finite position"),
    ("sigma", "standard deviation that is not finite and > 0"),
])
def test_bad_trajectories(case, match):
    t, pos, nav, sig = [0.0, 2.0, 1.0], np.zeros((3, 3)), _level(3), None
    if case == "order":
        pass
    elif case == "one":
        t, pos, nav = [0.0], np.zeros((1, 3)), _level(1)
    elif case == "nan":
        t = [0.0, 1.0, 2.0]
        pos = np.zeros((3, 3))
        pos[1, 2] = np.nan
    else:
        t = [0.0, 1.0, 2.0]
        sig = np.full((3, 6), 0.1)
        sig[2, 4] = 0.0
    with pytest.raises(InvalidInputError, match=match):
        Trajectory(t, pos, nav, sig)


def test_navigation_covariance_to_omega_phi_kappa():
    """Level flight north, no boresight: the camera's axes are the body's, so pitch is omega, roll is phi and heading
    is -kappa: their variances map one to one and the heading-x covariance changes sign."""
    R = body_rotation(0.0, 0.0, 0.0)[None]
    K = np.diag([0.01, 0.02, 0.03, 1e-6, 4e-6, 9e-6])
    K[0, 3] = K[3, 0] = 5e-5
    out = opk_covariance(R, K[None])[0]
    np.testing.assert_allclose(np.diag(out), [0.01, 0.02, 0.03, 4e-6, 9e-6, 1e-6], rtol=1e-6)
    np.testing.assert_allclose(out[0, 5], -5e-5, rtol=1e-6)
    assert abs(out[0, 3]) < 1e-12


# ---------------------------------------------------------------------------- files
def test_trajectory_csv_units_and_crs(tmp_path):
    p = tmp_path / "traj.csv"
    p.write_text("# crs=EPSG:32633\n# angles=deg\ntime,x,y,z,heading,pitch,roll,sx,sy,sz\n"
                 "0,0,0,100,359,0,0,0.05,0.05,0.1\n1,10,0,100,1,0,0,0.05,0.05,0.1\n")
    tf = read_trajectory_csv(p)
    assert tf.crs == "EPSG:32633"
    np.testing.assert_allclose(np.degrees(tf.trajectory.navigation[:, 0]), [359.0, 1.0])
    assert np.isnan(tf.trajectory.sigma[:, 3:]).all() and tf.trajectory.sigma[0, 2] == 0.1
    p.with_suffix(".prj").write_text("EPSG:4326")
    with pytest.raises(CRSError, match="contradicts the '# crs=' line"):
        read_trajectory_csv(p)
    q = tmp_path / "bad.csv"
    q.write_text("time,x,y,z,heading,pitch,roll,speed\n0,0,0,0,0,0,0,1\n")
    with pytest.raises(InvalidInputError, match=r"unknown column\(s\) \['speed'\]"):
        read_trajectory_csv(q)


def test_pose_extras_make_full_covariances(tmp_path):
    p = tmp_path / "poses.csv"
    p.write_text("image,x,y,z,omega,phi,kappa,sx,sy,sz,time,strip,corr_x_y,corr_y_z\n"
                 "a,0,0,100,0,0,0,0.1,0.2,0.3,5.0,s1,0.5,\n"
                 "b,10,0,100,0,0,0,0.1,0.2,0.3,6.0,s1,-0.25,0.1\n")
    ex = read_pose_extras(p)
    assert ex.strip == ("s1", "s1") and ex.time.tolist() == [5.0, 6.0]
    g = GnssObservations(("a", "b"), np.zeros((2, 3)), np.full((2, 3), 0.1))
    tab = read_pose_csv(p)
    gg = gnss_with_extras(g, ex, tab.poses, tab.sigma)
    np.testing.assert_allclose(gg.covariance[0], [[0.01, 0.01, 0.0], [0.01, 0.04, 0.0], [0.0, 0.0, 0.09]])
    np.testing.assert_allclose(gg.covariance[1, 1, 2], 0.1 * 0.2 * 0.3)
    assert gg.strip == ("s1", "s1") and gg.time.tolist() == [5.0, 6.0]
    p.write_text("image,x,y,z,omega,phi,kappa,sx,sy,sz,corr_x_y,corr_x_z,corr_y_z\n"
                 "a,0,0,100,0,0,0,0.1,0.2,0.3,0.9,0.9,-0.9\n")
    ex = read_pose_extras(p)
    tab = read_pose_csv(p)
    with pytest.raises(InvalidInputError, match=r"image 'a' \(line 2\): its correlation matrix is not positive"):
        gnss_with_extras(GnssObservations(("a",), np.zeros((1, 3)), np.ones((1, 3))), ex, tab.poses, tab.sigma)
    p.write_text("image,x,y,z,omega,phi,kappa,corr_x_y\na,0,0,100,0,0,0,1.5\n")
    with pytest.raises(InvalidInputError, match="line 2: correlation 'corr_x_y' of image 'a' must be in"):
        read_pose_extras(p)
    p.write_text("image,x,y,z,omega,phi,kappa,corr_x_w\na,0,0,100,0,0,0,0.5\n")
    with pytest.raises(InvalidInputError, match="unknown correlation column 'corr_x_w'"):
        read_pose_extras(p)


# ---------------------------------------------------------------------------- stereo block --trajectory
def _strip_crs(path):
    path.write_text("\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("# crs")) + "\n")


@pytest.fixture(scope="module")
def traj_block(tmp_path_factory):
    """A 2 x 6 synthetic block, its files (no CRS), and a trajectory CSV sampled at the exposure times and
    half-way between them, plus an image-times CSV."""
    d = tmp_path_factory.mktemp("traj")
    blk = make_block(7, strips=2, images_per_strip=6, n_points=700, gnss_noise_m=0.05, n_check=6)
    images, cam, poses, ctrl, ties, checks = write_block_files(d, blk)
    _strip_crs(poses)
    _strip_crs(ctrl)
    names = blk.tracks.images
    lab = np.array([int(n.split("_")[0][1:]) for n in names])
    order = np.array([int(n.split("_")[1]) for n in names])
    t = 600.0 * lab + 4.0 * order
    nav = navigation_from_rotation(np.array([p.rotation for p in blk.true_poses]))
    k = np.argsort(t)
    ts, ps, ns = t[k], blk.gnss.position[k], nav[k]
    # half-way samples on the chord (positions) and the mean heading (angles) between consecutive images
    tm = (ts[:-1] + ts[1:]) / 2
    pm = (ps[:-1] + ps[1:]) / 2
    hm = np.angle(np.exp(1j * ns[:-1, 0]) + np.exp(1j * ns[1:, 0]))
    nm = np.column_stack([np.mod(hm, 2 * np.pi), (ns[:-1, 1:] + ns[1:, 1:]) / 2])
    T = np.concatenate([ts, tm])
    o = np.argsort(T)
    P, N = np.concatenate([ps, pm])[o], np.concatenate([ns, nm])[o]
    traj = d / "traj.csv"
    rows = ["# angles=rad", "time,x,y,z,heading,pitch,roll,sx,sy,sz"]
    rows += [",".join(repr(float(v)) for v in (T[o][i], *P[i], *N[i], 0.05, 0.05, 0.05)) for i in range(len(o))]
    traj.write_text("\n".join(rows) + "\n")
    times = d / "times.csv"
    times.write_text("image,time,strip\n" + "".join(f"{n},{float(t[i])!r},s{lab[i]}\n"
                                                    for i, n in enumerate(names)))
    return d, blk, images, cam, poses, ctrl, ties, checks, traj, times


def test_block_from_a_trajectory_matches_the_pose_file(traj_block, tmp_path):
    """The trajectory sampled at the exposure times gives the pose file's GNSS positions (linear and cubic alike:
    the samples are at those times) and the truth's rotations; the block adjusts to the same check points."""
    d, blk, images, cam, poses, ctrl, ties, checks, traj, times = traj_block
    opts = BlockOptions(check_ids=checks, report=False, stac=False, trajectory=str(traj),
                        bundle=BundleOptions(image_sigma_px=0.5))
    r1 = run_block(images, out_dir=tmp_path / "t", camera=cam, poses=times, control=ctrl, options=opts, tracks=ties)
    r2 = run_block(images, out_dir=tmp_path / "p", camera=cam, poses=poses, control=ctrl, tracks=ties,
                   options=BlockOptions(check_ids=checks, report=False, stac=False,
                                        bundle=BundleOptions(image_sigma_px=0.5)))
    e1, e2 = r1.bundle.check_errors, r2.bundle.check_errors
    np.testing.assert_allclose(e1, e2, atol=2e-3)
    z = e1 / r1.bundle.check_std
    assert np.sqrt(np.mean(z ** 2, axis=0)).max() < 1.5
    assert any("GNSS: the positions of 12 images of times.csv" in ln for ln in r1.summary_lines())
    o = read_block_orientation(tmp_path / "t" / "orientation.json")
    truth = {p.image: p for p in blk.true_poses}
    dang = np.array([angles_from_matrix(truth[q.image].rotation.T @ q.rotation) for q in o.poses])
    assert np.degrees(np.abs(dang)).max() < 0.05


def _hashes(paths):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


@pytest.mark.parametrize("case,expect", [
    ("late", "image 's1_000': exposure time 9999.0 s is outside the trajectory 'traj.csv' span 0.0 .. 620.0 s"),
    ("no_poses", "--trajectory needs --poses"),
    ("nan", "line 5: column 'y' is not finite: 'nan'"),
    ("empty_strip", "empty strip of image 's0_002'"),
    ("unknown_image", "not given"),
    ("not_pd", "its correlation matrix is not positive definite"),
    ("drift_no_strip", "needs the strip of every image"),
])
def test_cli_bad_input_one_line_nothing_written(traj_block, tmp_path, case, expect):
    d, blk, images, cam, poses, ctrl, ties, checks, traj, times = traj_block
    out = tmp_path / "out"
    t_text = times.read_text().splitlines()
    f = tmp_path / "in.csv"
    args = ["block", *map(str, images), "--camera", str(cam), "--control", str(ctrl), "-o", str(out)]
    if case == "late":
        f.write_text("\n".join(t_text[:-1] + [",".join(t_text[-1].split(",")[:1] + ["9999.0", "s1"])]) + "\n")
        args += ["--poses", str(f), "--trajectory", str(traj)]
    elif case == "no_poses":
        args += ["--trajectory", str(traj)]
    elif case == "nan":
        lines = traj.read_text().splitlines()
        cells = lines[4].split(",")
        cells[2] = "nan"
        g = tmp_path / "traj_nan.csv"
        g.write_text("\n".join(lines[:4] + [",".join(cells)] + lines[5:]) + "\n")
        args += ["--poses", str(times), "--trajectory", str(g)]
    elif case == "empty_strip":
        f.write_text("\n".join(t_text[:3] + [t_text[3].rsplit(",", 1)[0] + ","] + t_text[4:]) + "\n")
        args += ["--poses", str(f), "--trajectory", str(traj)]
    elif case == "unknown_image":
        f.write_text("\n".join(t_text + ["ghost.tif,5.0,s0"]) + "\n")
        args += ["--poses", str(f), "--trajectory", str(traj)]
    elif case == "not_pd":
        lines = poses.read_text().splitlines()
        k = next(i for i, ln in enumerate(lines) if ln.startswith("image,"))
        lines[k] += ",corr_x_y,corr_x_z,corr_y_z"
        lines[k + 1:] = [ln + (",0.9,0.9,-0.9" if j == 2 else ",0,0,0") for j, ln in enumerate(lines[k + 1:])]
        f.write_text("\n".join(lines) + "\n")
        args += ["--poses", str(f)]
    elif case == "drift_no_strip":
        args += ["--poses", str(poses), "--gnss-drift", "shift"]
    ins = [p for p in (*images, cam, ctrl, traj, times, poses) if p.exists()]
    before = _hashes(ins)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code != 0
    assert expect in r.output, r.output
    assert "Traceback" not in r.output
    assert len([ln for ln in r.output.splitlines() if ln.startswith("Error")]) == 1
    assert not out.exists()
    assert _hashes(ins) == before


def test_cli_drift_per_strip_end_to_end(traj_block, tmp_path):
    """``stereo block --gnss-drift shift-drift`` on a pose CSV with time and strip columns whose GNSS positions
    carry a known shift and drift per strip, adjusted from its observations CSV (no images): the summary prints
    the estimates, within 2 std of the truth."""
    d, blk, images, cam, poses, ctrl, ties, checks, traj, times = traj_block
    names = blk.tracks.images
    lab = np.array([int(n.split("_")[0][1:]) for n in names])
    t = np.array([600.0 * lab[i] + 4.0 * int(n.split("_")[1]) for i, n in enumerate(names)])
    shift = np.array([[0.8, -0.5, 0.6], [-0.6, 0.7, -0.4]])
    drift = np.array([[0.02, -0.01, 0.015], [-0.015, 0.02, 0.01]])
    tm = np.array([t[lab == k].mean() for k in range(2)])
    lines = poses.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("image,"))
    out_lines = lines[:k] + [lines[k] + ",time,strip"]
    for ln in lines[k + 1:]:
        c = ln.split(",")
        i = names.index(c[0])
        xyz = np.array([float(v) for v in c[1:4]]) + shift[lab[i]] + drift[lab[i]] * (t[i] - tm[lab[i]])
        out_lines.append(",".join([c[0], *(repr(float(v)) for v in xyz), *c[4:], repr(float(t[i])), f"s{lab[i]}"]))
    pf = tmp_path / "poses_drift.csv"
    pf.write_text("\n".join(out_lines) + "\n")
    obs = _observations_csv(tmp_path / "obs.csv", ties)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["block", "--observations", str(obs), "--camera", str(cam), "--poses", str(pf),
                                 "--control", str(ctrl), "--check", ",".join(checks), "--gnss-drift", "shift-drift",
                                 "--robust", "none", "--no-variance-components", "--no-stac", "--no-report",
                                 "-o", str(out)])
    assert r.exit_code == 0, r.output
    got = {}
    for ln in r.output.splitlines():
        if ln.startswith("gnss shift") or ln.startswith("gnss drift"):
            name, rest = ln.split(":")
            v, s = rest.split("+-")
            got[name] = (float(v), float(s.split()[0]))
    assert len(got) == 12, r.output
    for s_ in range(2):
        for a, ax in enumerate("xyz"):
            v, sd = got[f"gnss shift s{s_} {ax}"]
            assert abs(v / 1000 - shift[s_, a]) < 2 * sd / 1000 + 1e-3, (s_, ax, v, sd)
            v, sd = got[f"gnss drift s{s_} {ax}"]
            assert abs(v / 1000 - drift[s_, a]) < 2 * sd / 1000 + 1e-5, (s_, ax, v, sd)
    assert (out / "orientation.json").is_file()


def _observations_csv(path, tr):
    path.write_text("image,id,col,row\n" + "".join(
        f"{tr.images[tr.obs_image[m]]},{tr.point_ids[tr.obs_point[m]]},{float(tr.obs_pixel[m, 0])!r},"
        f"{float(tr.obs_pixel[m, 1])!r}\n" for m in range(tr.n_obs)))
    return path


def test_cli_trajectory_with_observations(traj_block, tmp_path):
    """``stereo block --observations obs.csv --poses times.csv --trajectory traj.csv``: no images; the same
    adjustment as from the pose CSV of the same positions and angles (projection centres within 2 mm), within
    0.15 m and 0.05 deg of the truth."""
    d, blk, images, cam, poses, ctrl, ties, checks, traj, times = traj_block
    obs = _observations_csv(tmp_path / "obs.csv", ties)
    common = ["--camera", str(cam), "--control", str(ctrl), "--check", ",".join(checks), "--no-report", "--no-stac"]
    r = CliRunner().invoke(cli, ["block", "--observations", str(obs), "--poses", str(times), "--trajectory",
                                 str(traj), *common, "-o", str(tmp_path / "t")])
    assert r.exit_code == 0, r.output
    assert "check: 6 points" in r.output
    # the pose CSV with the truth's angles (the trajectory's), the same GNSS positions
    lines = poses.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("image,"))
    truth = {p.image: p for p in blk.true_poses}
    rows = lines[:k + 1]
    for ln in lines[k + 1:]:
        c = ln.split(",")
        a = np.degrees(angles_from_matrix(truth[c[0]].rotation))
        rows.append(",".join([*c[:4], *(repr(float(v)) for v in a), *c[7:]]))
    pf = tmp_path / "poses_true_angles.csv"
    pf.write_text("\n".join(rows) + "\n")
    r2 = CliRunner().invoke(cli, ["block", "--observations", str(obs), "--poses", str(pf), *common,
                                  "-o", str(tmp_path / "p")])
    assert r2.exit_code == 0, r2.output
    o = read_block_orientation(tmp_path / "t" / "orientation.json")
    o2 = {q.image: q for q in read_block_orientation(tmp_path / "p" / "orientation.json").poses}
    np.testing.assert_allclose([q.position for q in o.poses], [o2[q.image].position for q in o.poses], atol=2e-3)
    err = np.array([q.position - truth[q.image].position for q in o.poses])
    assert np.abs(err).max() < 0.15, err
    dang = np.array([angles_from_matrix(truth[q.image].rotation.T @ q.rotation) for q in o.poses])
    assert np.degrees(np.abs(dang)).max() < 0.05



def test_navigation_file_correlations_give_a_six_by_six_covariance(tmp_path):
    """A heading/pitch/roll pose CSV with angle std and corr_y_roll: each image gets a 6 x 6 covariance of x, y, z,
    omega, phi, kappa; level flight north: roll is phi, so the y-phi covariance is corr * sy * sroll."""
    p = tmp_path / "nav.csv"
    p.write_text("# angles=deg\nimage,x,y,z,heading,pitch,roll,sx,sy,sz,sheading,spitch,sroll,corr_y_roll\n"
                 "a,0,0,100,0,0,0,0.1,0.2,0.3,0.02,0.01,0.01,0.5\n"
                 "b,10,0,100,0,0,0,0.1,0.2,0.3,0.02,0.01,0.01,-0.5\n")
    tab = read_pose_csv(p)
    ex = read_pose_extras(p)
    assert ex.angle_system == "navigation"
    ang = np.array([angles_from_matrix(q.rotation) for q in tab.poses])
    g = GnssObservations(("a", "b"), np.zeros((2, 3)), np.full((2, 3), 0.1), angles=ang,
                         sigma_rad=np.full((2, 3), 1e-4))
    gg = gnss_with_extras(g, ex, tab.poses, tab.sigma)
    assert gg.covariance.shape == (2, 6, 6)
    sroll = np.radians(0.01)
    np.testing.assert_allclose(gg.covariance[:, 1, 4], [0.5 * 0.2 * sroll, -0.5 * 0.2 * sroll], rtol=1e-5)
    np.testing.assert_allclose(gg.sigma_rad[0], np.radians([0.01, 0.01, 0.02]), rtol=1e-5)
