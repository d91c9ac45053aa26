"""Issue 24, the block items: every figure ``stereo block`` writes or prints is the one computed for its result.

- item 1: ``poses.csv``'s standard deviations are the bundle's, column by column (they were swapped);
- item 4: a control point all of whose rays are flagged as blunders is rejected by id, not counted;
- item 5: the datum statement's precision is that of the points written; the iterations stay within
  ``--max-iterations``; variance factors estimated from little redundancy are flagged;
- item 7: an OpenSfM reconstruction's topocentric frame, and OpenDroneMap's georeferenced one, are read as
  their programs define them and every output states its CRS;
- item 8: the reconstruction's own GPS fixes the datum; without it, the job stops before any matching and
  names ``--gnss-sigma``; the datum message names CLI options.

The blocks are :func:`tests.support.block_synthetic.make_block`'s, written as files
(:mod:`tests.support.block_files`) with their tie tracks handed in (placeholder images).
"""

from __future__ import annotations

import json
import re

import laspy
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rectify.errors import CRSError, EstimationError, InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.crs import parse_crs, transform_xyz
from stereo.actions.block import BlockOptions, run_block
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.types import Pose, project_pixel
from stereo.formats.block import read_block_orientation
from stereo.formats.opensfm import odm_affine, read_odm_coords, read_opensfm, topocentric_crs_wkt
from stereo.formats.points import read_points_csv
from stereo.formats.poses import read_pose_csv
from tests.support.block_files import write_block_files
from tests.support.block_synthetic import make_block

REF = (10.5, 50.25, 300.0)  # lon, lat (deg), h (m): the topocentric origin of the synthetic reconstructions
CAM0 = Camera(focal_length_mm=100.0, pixel_size_mm=0.01, width=2000, height=1500)


# ------------------------------------------------------------------ one run with a rejected control point
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A block with GNSS and control, one control point measured 40 px off in every image (so every ray of it
    is flagged), run with the defaults of ``stereo block`` (Tukey, variance components, 100 iterations)."""
    blk = make_block(0)
    t = blk.tracks
    cid = [c for c, chk in zip(blk.control.ids, blk.control.check, strict=True) if not chk][0]
    rows = [k for k in range(t.n_obs) if t.point_ids[t.obs_point[k]] == cid]
    ang = np.random.default_rng(1).uniform(0, 2 * np.pi, len(rows))
    px = t.obs_pixel[rows] + 40.0 * np.column_stack([np.cos(ang), np.sin(ang)])
    tmp = tmp_path_factory.mktemp("seams")
    images, cam, poses, ctrl, ties, checks = write_block_files(tmp, blk, pixels={cid: px})
    out = tmp / "out"
    opts = BlockOptions(check_ids=checks, bundle=BundleOptions(robust="tukey", image_sigma_px=0.5,
                                                               variance_components=True, max_iterations=100),
                        frame="map")  # the synthetic block is Cartesian in its (UTM-labelled) coordinates
    res = run_block(images, out_dir=out, camera=cam, poses=poses, control=ctrl, tracks=ties, options=opts)
    return res, out, blk, cid, len(rows)


def test_pose_csv_standard_deviations_are_the_bundles_column_by_column(run):
    """Item 1: sx,sy,sz are the position std (m), somega,sphi,skappa the angle std (deg in the file)."""
    res, out, *_ = run
    b = res.bundle
    table = read_pose_csv(out / "poses.csv")
    sd = np.sqrt(np.diagonal(np.asarray(b.pose_covariance), axis1=1, axis2=2))  # omega, phi, kappa, x, y, z
    assert table.sigma is not None
    np.testing.assert_allclose(table.sigma[:, :3], sd[:, 3:], rtol=1e-12)   # sx, sy, sz, metres
    np.testing.assert_allclose(table.sigma[:, 3:], sd[:, :3], rtol=1e-12)   # read back in radians
    text = (out / "poses.csv").read_text().splitlines()
    head = text.index(next(s for s in text if s.startswith("image,")))
    cols = text[head].split(",")
    first = dict(zip(cols, text[head + 1].split(","), strict=True))
    assert float(first["sz"]) == pytest.approx(sd[0, 5], rel=1e-12)
    assert float(first["skappa"]) == pytest.approx(np.degrees(sd[0, 2]), rel=1e-12)
    assert float(first["sx"]) < 1.0 and float(first["somega"]) < 0.1  # metres and degrees, not swapped


def test_observations_csv_residuals_are_adjusted_minus_observed(run):
    """observations.csv says residual = adjusted - observed: the adjusted point projected minus the measurement."""
    res, out, *_ = run
    b, t = res.bundle, res.tracks
    lines = (out / "observations.csv").read_text().splitlines()
    head = lines[0].split(",")
    k = 5
    row = dict(zip(head, lines[1 + k].split(","), strict=True))
    pose = b.poses[t.obs_image[k]]
    proj = project_pixel(b.cameras[pose.camera], pose, np.asarray(b.points)[t.obs_point[k]][None])[0]
    v = proj - t.obs_pixel[k]
    assert float(row["residual_x_px"]) == pytest.approx(v[0], abs=2e-5)
    assert float(row["residual_y_px"]) == pytest.approx(v[1], abs=2e-5)


def test_control_point_with_every_ray_flagged_is_rejected_by_id_and_not_counted(run):
    """Item 4: named as rejected on the console and in the report; not in the count, the RMS or the table."""
    res, out, blk, cid, n_rays = run
    b = res.bundle
    n_ctrl = int((~blk.control.check).sum())
    assert b.rejected_control == (cid,)
    assert cid not in b.control_ids and len(b.control_ids) == n_ctrl - 1 == res.n_control
    text = "\n".join(res.summary_lines())
    assert f"control: {n_ctrl - 1} points" in text
    assert f"rejected (every ray flagged as a blunder): ['{cid}']" in text
    assert f"control point {cid} rejected: all {n_rays} of its image observations were flagged" in text
    assert f"control at {n_ctrl - 1} points" in text
    rep = json.loads((out / "report" / "report.json").read_text())
    assert rep["summary"]["control_rejected"] == [cid] and rep["summary"]["control_points"] == n_ctrl - 1
    ctrl = [tb for tb in rep["tables"] if tb["step"] == "bundle: control points"][0]
    assert ctrl["summary"]["n_points"] == n_ctrl - 1
    csv = (out / "report" / "bundle_control_points.csv").read_text()
    assert f"\n{cid}," not in csv
    # the observed columns are the given coordinates, not zeros
    row = [ln for ln in csv.splitlines() if ln and not ln.startswith("#")][1].split(",")
    assert abs(float(row[1])) > 1.0 and abs(float(row[3])) > 1.0
    orient = read_block_orientation(out / "orientation.json")
    assert any(f"control point {cid} rejected" in s for s in orient.datum)


def test_datum_height_std_is_that_of_the_written_points(run):
    """Item 5: the datum statement's median and 95th percentile are those of points.csv's tie points."""
    res, out, *_ = run
    b = res.bundle
    line = next(s for s in b.datum if "predicted height std" in s)
    m = re.search(r"median ([\d.]+) m, 95th percentile ([\d.]+) m", line)
    assert m, line
    pts = read_points_csv(out / "points.csv")
    assert pts.std is not None
    ctrl = set(b.control_ids)
    sz = np.array([s[2] for i, s in zip(pts.ids, pts.std, strict=True) if i not in ctrl])
    assert float(m.group(1)) == pytest.approx(np.median(sz), abs=6e-4)
    assert float(m.group(2)) == pytest.approx(np.percentile(sz, 95), abs=6e-4)
    assert f"{len(sz)} tie points written" in line


def test_iterations_stay_within_the_limit_and_say_so(run):
    """Item 5: the iterations of every variance-component round count against --max-iterations."""
    res, *_ = run
    b = res.bundle
    assert b.iterations <= 100 and b.iteration_limit == 100
    text = "\n".join(res.summary_lines())
    assert f"{b.iterations} iterations (limit 100)" in text
    if b.iterations == 100:
        assert "stopped at the iteration limit (100 iterations in all)" in text


def test_iteration_limit_over_variance_rounds_in_the_adjustment():
    b = make_block(0)
    opts = BundleOptions(image_sigma_px=0.5 / 3, variance_components=True, robust="tukey", max_iterations=30)
    r = adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points, control=b.control, gnss=b.gnss,
                      options=opts)
    assert r.iterations <= 30 and r.converged
    assert any("variance components stopped at the iteration limit (30 iterations in all)" in w for w in r.warnings)


def test_variance_factor_from_little_redundancy_is_flagged(run):
    """Item 5: a group whose variance factor rests on a redundancy below 10 is flagged with the number, on the
    console and in the report."""
    res, out, *_ = run
    b = res.bundle
    weak = {g: r for g, r in (b.variance_estimated or {}).items() if min(r, b.redundancy_groups[g]) < 10}
    assert weak, (b.variance_estimated, b.redundancy_groups)
    g, r_est = next(iter(weak.items()))
    text = "\n".join(res.summary_lines())
    assert f"group {g}: variance factor {b.variance_factors[g]:.3f} estimated from a redundancy of {r_est:.1f}" \
        in text
    assert re.search(rf"group {g}: sigma0 [\d.]+, redundancy [\d.]+, variance factor [\d.]+ \(estimated from a "
                     rf"redundancy of {r_est:.1f}", text)
    rep = json.loads((out / "report" / "report.json").read_text())
    assert any(f"estimated from a redundancy of {r_est:.1f}" in w for w in rep["summary"]["warnings"])
    # a group below 2 is not estimated, and says so
    low = [g for g in b.sigma0_groups if g not in (b.variance_estimated or {})]
    for g in low:
        assert re.search(rf"group {g}: .*\(not estimated: redundancy below 2\)", text)


def test_console_gnss_rms_is_labelled_per_component_and_3d(run):
    res, out, *_ = run
    g = np.asarray(res.bundle.gnss_residuals)
    text = "\n".join(res.summary_lines())
    assert f"GNSS residuals: RMS per component {np.sqrt(np.mean(g ** 2)):.3f} m" in text
    assert f"RMS of the 3D residual {np.sqrt(np.mean(np.sum(g ** 2, axis=1))):.3f} m" in text
    rep = json.loads((out / "report" / "report.json").read_text())
    assert rep["summary"]["gnss_rms_3d_m"] == pytest.approx(np.sqrt(np.mean(np.sum(g ** 2, axis=1))))
    assert rep["summary"]["gnss_rms_per_component_m"] == pytest.approx(np.sqrt(np.mean(g ** 2)))


# ------------------------------------------------------------------ OpenSfM and OpenDroneMap
def _shot(pose: Pose) -> dict:
    R_cw = np.diag([1.0, -1.0, -1.0]) @ pose.rotation.T  # world -> OpenCV camera axes
    return {"camera": "cam", "rotation": Rotation.from_matrix(R_cw).as_rotvec().tolist(),
            "translation": (-R_cw @ pose.position).tolist()}


def _reconstruction(blk, poses, *, gps=True, dop=0.05, reference=REF, shift=(0.0, 0.0, 0.0)) -> list:
    s = max(CAM0.width, CAM0.height)
    shots = {}
    for k, p in enumerate(poses):
        sh = _shot(Pose(p.image, p.camera, p.position + shift, p.rotation))
        if gps:
            sh["gps_position"] = (blk.gnss.position[k] + shift).tolist()
            sh["gps_dop"] = dop
        shots[p.image] = sh
    rec = {"cameras": {"cam": {"projection_type": "perspective", "width": CAM0.width, "height": CAM0.height,
                               "focal": CAM0.focal_px / s, "k1": 0.0, "k2": 0.0}}, "shots": shots, "points": {}}
    if reference is not None:
        rec["reference_lla"] = {"longitude": reference[0], "latitude": reference[1], "altitude": reference[2]}
    return [rec]


@pytest.fixture(scope="module")
def small_block():
    """A 3 x 6 block flown at 300 m (about 0.9 x 0.7 km), centred on the topocentric origin."""
    blk = make_block(2, flying_height_m=300.0, relief_m=20.0, camera=CAM0, n_points=500)
    return blk


def _placeholders(tmp_path, blk):
    d = tmp_path / "img"
    d.mkdir()
    out = []
    for n in blk.tracks.images:
        (d / n).write_bytes(b"placeholder")
        out.append(d / n)
    return out


def _ties(blk):
    ids = set(blk.control.ids)
    return blk.tracks.subset(np.array([blk.tracks.point_ids[i] not in ids for i in blk.tracks.obs_point]))


def test_opensfm_topocentric_outputs_state_their_crs(small_block, tmp_path):
    """Item 7: a reconstruction with reference_lla: every output in OpenSfM's topocentric frame, as a CRS."""
    blk = small_block
    rec = tmp_path / "reconstruction.json"
    rec.write_text(json.dumps(_reconstruction(blk, blk.initial_poses)))
    out = tmp_path / "out"
    res = run_block(_placeholders(tmp_path, blk), out_dir=out, camera=None, poses=rec, tracks=_ties(blk),
                    options=BlockOptions(gnss_sigma_m=(0.05, 0.05, 0.05)))
    o = read_block_orientation(out / "orientation.json")
    assert o.crs is not None
    crs = parse_crs(o.crs)
    assert crs.is_projected and "topocentric" in o.crs.lower()
    assert o.reference_lonlat_h is not None
    np.testing.assert_allclose(o.reference_lonlat_h, REF)
    assert o.frame is not None and "topocentric east-north-up" in o.frame and "lat 50.25000000" in o.frame
    # the CRS is the topocentric frame about the reference: its origin is the reference point
    np.testing.assert_allclose(transform_xyz(o.crs, "EPSG:4979", [[0.0, 0.0, 0.0]])[0], REF, atol=1e-7)
    assert parse_crs(read_pose_csv(out / "poses.csv").crs or "").equals(crs)
    las = laspy.read(out / "points.las")
    assert las.header.parse_crs() is not None and las.header.parse_crs().equals(crs)
    assert "frame: topocentric east-north-up frame of OpenSfM" in "\n".join(res.summary_lines())


def test_opensfm_gps_fixes_the_datum_without_gnss_sigma(small_block, tmp_path):
    """Item 8: the reconstruction's gps_position, weighted by its gps_dop, are the GNSS observations."""
    blk = small_block
    rec = tmp_path / "reconstruction.json"
    rec.write_text(json.dumps(_reconstruction(blk, blk.initial_poses, dop=0.05)))
    res = run_block(_placeholders(tmp_path, blk), out_dir=tmp_path / "out", camera=None, poses=rec,
                    tracks=_ties(blk))
    text = "\n".join(res.summary_lines())
    n = len(blk.true_poses)
    assert f"GNSS: the gps_position of {n} of {n} shots of reconstruction.json (sigma = its gps_dop, median 0.05 m)" \
        in text
    assert f"datum: GNSS positions of {n} images, no control" in text
    truth = {p.image: p for p in blk.true_poses}
    err = np.array([p.position - truth[p.image].position for p in res.bundle.poses])
    assert np.all(np.abs(err) < 4 * res.bundle.pose_std[:, 3:] + 0.02), (err, res.bundle.pose_std[:, 3:])


def test_opensfm_without_gps_stops_before_any_matching_naming_gnss_sigma(small_block, tmp_path):
    """Item 8: no GPS, no control: one line naming --gnss-sigma and --free-network, before the images are read
    (they are placeholders: matching them would fail otherwise), nothing written."""
    blk = small_block
    rec = tmp_path / "reconstruction.json"
    rec.write_text(json.dumps(_reconstruction(blk, blk.initial_poses, gps=False)))
    out = tmp_path / "out"
    with pytest.raises(EstimationError) as info:
        run_block(_placeholders(tmp_path, blk), out_dir=out, camera=None, poses=rec)
    msg = str(info.value)
    assert "datum defect" in msg and "reconstruction.json has no gps_position" in msg
    assert "--gnss-sigma" in msg and "--free-network" in msg and "free_network" not in msg
    assert not out.exists()


def test_bundle_datum_defect_names_the_cli_option():
    b = make_block(0)
    with pytest.raises(EstimationError, match="--free-network") as info:
        adjust_bundle(b.cameras, b.initial_poses, b.tracks, b.initial_points)
    assert "free_network" not in str(info.value)


def _odm_affine(ref):
    """OpenSfM's export_geocoords (ODM's default, affine): the linear map of topocentric -> UTM at the origin,
    as OpenSfM computes it (the images of the unit vectors)."""
    wkt = topocentric_crs_wkt(ref)
    q = transform_xyz(wkt, "EPSG:32632", np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, 0]]))
    A = (q[:3] - q[3]).T
    return A, q[3]


def test_odm_affine_is_opensfms_and_close_to_the_projection():
    A, b = odm_affine(REF, "EPSG:32632")
    A2, b2 = _odm_affine(REF)
    np.testing.assert_allclose(A, A2)
    np.testing.assert_allclose(b, b2)
    assert np.degrees(np.arctan2(A[1, 0], A[0, 0])) == pytest.approx(1.153, abs=1e-3)  # grid convergence
    P = np.array([[1000.0, 0.0, 0.0], [0.0, 1000.0, 0.0]])
    d = transform_xyz(topocentric_crs_wkt(REF), "EPSG:32632", P) - (P @ A.T + b)
    assert np.abs(d[:, :2]).max() < 0.005 and np.allclose(d[:, 2], 0.078, atol=0.002)  # curvature, 1 km


def test_odm_georeferenced_reconstruction_is_read_in_its_utm_crs(small_block, tmp_path):
    """Item 7: ODM's reconstruction.json (UTM minus the coords.txt offset; reconstruction.topocentric.json beside
    it): the outputs are in EPSG:32632 with the offset added back, as ODM's orthophoto and DSM."""
    blk = small_block
    A, b0 = _odm_affine(REF)
    offset = np.array([np.floor(b0[0]), np.floor(b0[1]), 0.0])
    U, _, Vt = np.linalg.svd(A)
    Q = U @ Vt
    odm_poses = [Pose(p.image, p.camera, A @ p.position + b0 - offset, Q @ p.rotation) for p in blk.initial_poses]
    proj = tmp_path / "odm"
    (proj / "opensfm").mkdir(parents=True)
    (proj / "odm_georeferencing").mkdir()
    rec = _reconstruction(blk, odm_poses, dop=0.05)
    for k, p in enumerate(blk.initial_poses):  # gps_position stays topocentric in ODM's copy
        rec[0]["shots"][p.image]["gps_position"] = blk.gnss.position[k].tolist()
    (proj / "opensfm" / "reconstruction.json").write_text(json.dumps(rec))
    (proj / "opensfm" / "reconstruction.topocentric.json").write_text(
        json.dumps(_reconstruction(blk, blk.initial_poses, dop=0.05)))
    (proj / "odm_georeferencing" / "coords.txt").write_text(f"WGS84 UTM 32N\n{offset[0]:.0f} {offset[1]:.0f}\n")
    r = read_opensfm(proj / "opensfm" / "reconstruction.json")
    assert r.crs == "EPSG:32632" and r.offset is not None
    np.testing.assert_allclose(r.offset, offset)
    out = tmp_path / "out"
    res = run_block(_placeholders(tmp_path, blk), out_dir=out, camera=None,
                    poses=proj / "opensfm" / "reconstruction.json", tracks=_ties(blk))
    o = read_block_orientation(out / "orientation.json")
    assert o.crs == "EPSG:32632" and "OpenDroneMap's georeferenced frame EPSG:32632" in (o.frame or "")
    truth = {p.image: A @ p.position + b0 for p in blk.true_poses}  # ODM's frame, full UTM coordinates
    err = np.array([p.position - truth[p.image] for p in o.poses])
    assert np.all(np.abs(err) < 4 * o.std_errors[:, 3:] + 0.02), (err, o.std_errors[:, 3:])
    assert laspy.read(out / "points.las").header.parse_crs().to_epsg() == 32632
    assert "frame: OpenDroneMap's georeferenced frame EPSG:32632" in "\n".join(res.summary_lines())


def test_odm_georeferenced_reconstruction_without_coords_txt_is_refused(small_block, tmp_path):
    blk = small_block
    d = tmp_path / "opensfm"
    d.mkdir()
    (d / "reconstruction.json").write_text(json.dumps(_reconstruction(blk, blk.initial_poses)))
    (d / "reconstruction.topocentric.json").write_text(json.dumps(_reconstruction(blk, blk.initial_poses)))
    with pytest.raises(InvalidInputError, match=r"OpenDroneMap's georeferenced reconstruction .*coords\.txt"):
        read_opensfm(d / "reconstruction.json")
    assert read_opensfm(d / "reconstruction.topocentric.json").crs is not None  # the topocentric one reads


@pytest.mark.parametrize("head, crs", [("WGS84 UTM 32N", "EPSG:32632"), ("WGS84 UTM 18S", "EPSG:32718"),
                                       ("EPSG:25833", "EPSG:25833"),
                                       ("+proj=utm +zone=32 +datum=WGS84 +units=m +no_defs", "EPSG:32632")])
def test_odm_coords_file(tmp_path, head, crs):
    p = tmp_path / "coords.txt"
    p.write_text(f"{head}\n440143 4588391\n1.0 2.0 3.0\n")
    got, off = read_odm_coords(p)
    assert parse_crs(got).equals(parse_crs(crs))
    np.testing.assert_allclose(off, [440143, 4588391, 0])
    p.write_text("WGS84 UTM 99X\n1 2\n")
    with pytest.raises(CRSError, match="line 1: unknown CRS header 'WGS84 UTM 99X'"):
        read_odm_coords(p)
    p.write_text(f"{head}\n1 zwei\n")
    with pytest.raises(InvalidInputError, match="line 2: the offset must be two numbers"):
        read_odm_coords(p)


def test_opensfm_reconstruction_converted_into_the_control_crs(small_block, tmp_path):
    """Control in UTM, a topocentric reconstruction: poses converted through pyproj, rotations turned by the
    grid convergence (about 1.15 deg here), so the images see the same ground points."""
    blk = small_block
    rec = tmp_path / "reconstruction.json"
    rec.write_text(json.dumps(_reconstruction(blk, blk.true_poses, gps=False)))
    r = read_opensfm(rec)
    u = r.to_crs("EPSG:32632")
    assert u.crs == "EPSG:32632" and "converted from topocentric" in u.frame
    X = blk.true_points[:200]
    Xu = transform_xyz(r.crs, "EPSG:32632", X)
    cam = r.cameras["cam"]
    worst = 0.0
    for p, q in zip(r.poses, u.poses, strict=True):
        a, b = project_pixel(cam, p, X), project_pixel(cam, q, Xu)
        inside = np.isfinite(a).all(axis=1) & (np.abs(a[:, 0] - 1000) < 1000) & (np.abs(a[:, 1] - 750) < 750)
        worst = max(worst, float(np.abs(a[inside] - b[inside]).max(initial=0.0)))
    assert worst < 0.5, worst  # without the rotation: some 20 px


def test_odm_project_gcps_fix_the_datum(small_block, tmp_path):
    """Item 8: an ODM project without GPS in its reconstruction but with its gcp_list.txt: the GCPs are the
    control (named on the console), read in the reconstruction's CRS."""
    blk = small_block
    A, b0 = _odm_affine(REF)
    offset = np.array([np.floor(b0[0]), np.floor(b0[1]), 0.0])
    U, _, Vt = np.linalg.svd(A)
    Q = U @ Vt
    proj = tmp_path / "odm"
    (proj / "opensfm").mkdir(parents=True)
    (proj / "odm_georeferencing").mkdir()
    odm_poses = [Pose(p.image, p.camera, A @ p.position + b0 - offset, Q @ p.rotation) for p in blk.initial_poses]
    (proj / "opensfm" / "reconstruction.json").write_text(json.dumps(_reconstruction(blk, odm_poses, gps=False)))
    (proj / "opensfm" / "reconstruction.topocentric.json").write_text(
        json.dumps(_reconstruction(blk, blk.initial_poses, gps=False)))
    (proj / "odm_georeferencing" / "coords.txt").write_text(f"WGS84 UTM 32N\n{offset[0]:.0f} {offset[1]:.0f}\n")
    t = blk.tracks
    used = [c for c, chk in zip(blk.control.ids, blk.control.check, strict=True) if not chk]
    where = {c: k for k, c in enumerate(blk.control.ids)}
    lines = ["WGS84 UTM 32N"]
    for k in range(t.n_obs):
        pid = t.point_ids[t.obs_point[k]]
        if pid in used:
            g = A @ blk.control.xyz[where[pid]] + b0
            lines.append(f"{g[0]:.4f} {g[1]:.4f} {g[2]:.4f} {t.obs_pixel[k, 0]:.3f} {t.obs_pixel[k, 1]:.3f} "
                         f"{t.images[t.obs_image[k]]} {pid}")
    (proj / "odm_georeferencing" / "gcp_list.txt").write_text("\n".join(lines) + "\n")
    res = run_block(_placeholders(tmp_path, blk), out_dir=tmp_path / "out", camera=None,
                    poses=proj / "opensfm" / "reconstruction.json", tracks=_ties(blk))
    text = "\n".join(res.summary_lines())
    assert f"control: the {len(used)} GCPs of " in text and "gcp_list.txt' (OpenDroneMap gcp_list.txt" in text
    assert f"datum: no GNSS, control at {len(used)} points ({len(used)} full" in text
    truth = {p.image: A @ p.position + b0 for p in blk.true_poses}
    err = np.array([p.position - truth[p.image] for p in res.bundle.poses])
    assert np.all(np.abs(err) < 4 * res.bundle.pose_std[:, 3:] + 0.05), (err, res.bundle.pose_std[:, 3:])
