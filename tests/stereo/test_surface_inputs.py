"""The orientation `stereo surface` reads: a `stereo block` folder or block orientation JSON, or another tool's
poses and cameras (stereo.actions.surface_inputs)."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine

from rectify.errors import InvalidInputError
from rectify.formats.orthority import write_ext_param, write_int_param
from rectify.raster.io import write_raster
from stereo.actions.surface_inputs import TOPOCENTRIC_METHOD, dem_ground_z, load_orientation
from stereo.block.types import Pose
from stereo.formats.block import block_orientation_text
from tests.support.block_example import CAM, CRS, E0, N0, write_example_block, write_example_reconstruction

R0 = np.diag([1.0, -1.0, -1.0])  # looking down


def _poses() -> list[Pose]:
    return [Pose(f"img{i}.tif", "cam", np.array([E0 + 30.0 * i, N0, 150.0]), R0) for i in range(3)]


def _orthority(tmp_path, camera_id="cam"):
    ext = write_ext_param(tmp_path / "ext_param.geojson", {p.image: {"position": p.position, "rotation": p.rotation,
                                                                     "camera": camera_id} for p in _poses()}, CRS)
    intr = write_int_param(tmp_path / "int_param.yaml", {camera_id: CAM})
    return ext, intr


def test_block_folder_and_json_are_read_as_ours(tmp_path):
    (tmp_path / "orientation.json").write_text(block_orientation_text({"cam": CAM}, _poses(), crs=CRS))
    for arg in (tmp_path, tmp_path / "orientation.json"):
        so = load_orientation(arg)
        assert so.ours and so.path == tmp_path / "orientation.json" and so.folder == tmp_path
        assert [p.image for p in so.orientation.poses] == ["img0.tif", "img1.tif", "img2.tif"]
        assert so.orientation.crs == CRS


def test_orthority_files_give_the_same_orientation(tmp_path):
    """orthority's ext_param + int_param: the same poses (to the file's precision), the camera, the CRS; no
    standard errors (the orientation's share of sigma_Z is then none)."""
    ext, intr = _orthority(tmp_path)
    so = load_orientation(ext, camera=intr)
    assert not so.ours and so.inputs == (ext, intr) and so.orientation.crs == CRS
    for got, want in zip(so.orientation.poses, _poses(), strict=True):
        assert got.image == want.image and got.camera == "cam"
        np.testing.assert_allclose(got.position, want.position, atol=1e-6)
        np.testing.assert_allclose(got.rotation, want.rotation, atol=1e-9)
    assert so.orientation.cameras["cam"].focal_length_mm == CAM.focal_length_mm
    assert np.isnan(so.orientation.std_errors).all() and so.orientation.std_errors.shape == (3, 6)


def test_a_camera_file_of_one_camera_serves_poses_naming_another_id(tmp_path):
    ext, _ = _orthority(tmp_path, camera_id="dmc")
    intr = write_int_param(tmp_path / "other.yaml", {"something": CAM})
    so = load_orientation(ext, camera=intr)
    assert so.orientation.cameras["dmc"].width == CAM.width


@pytest.mark.parametrize("case, message", [
    ("missing", "orientation not found: "),
    ("empty folder", "no orientation.json in the orientation folder"),
    ("no camera", "holds no camera 'cam': pass --camera"),
    ("camera with ours", "--camera is for another tool's pose file"),
    ("geo.txt", "has positions only (no rotations)"),
])
def test_bad_orientations_are_named(tmp_path, case, message):
    ext, intr = _orthority(tmp_path)
    (tmp_path / "orientation.json").write_text(block_orientation_text({"cam": CAM}, _poses(), crs=CRS))
    (tmp_path / "empty").mkdir()
    (tmp_path / "geo.txt").write_text(f"{CRS}\nimg0.tif {E0} {N0} 150\nimg1.tif {E0 + 30} {N0} 150\n")
    args = {"missing": (tmp_path / "nope.json", None), "empty folder": (tmp_path / "empty", None),
            "no camera": (ext, None), "camera with ours": (tmp_path, intr),
            "geo.txt": ("odm-geo:" + str(tmp_path / "geo.txt"), None)}[case]
    with pytest.raises(InvalidInputError, match="^" + "|".join([".*" + message.replace("(", r"\(")
                                                               .replace(")", r"\)")])) as info:
        load_orientation(args[0], camera=args[1])
    assert "\n" not in str(info.value)


def test_dem_ground_z_is_the_median_of_the_dem_at_the_points(tmp_path):
    h = np.add.outer(np.arange(20.0), np.arange(30.0))  # height = row + col
    write_raster(tmp_path / "dem.tif", h.astype(np.float32), Affine(10, 0, E0, 0, -10, N0 + 200), CRS)
    xy = np.array([[E0 + 5, N0 + 195], [E0 + 105, N0 + 195], [E0 + 205, N0 + 95]])   # cells (0,0), (0,10), (10,20)
    assert dem_ground_z(tmp_path / "dem.tif", xy, CRS) == pytest.approx(10.0, abs=1e-6)
    assert dem_ground_z(tmp_path / "dem.tif", xy + 1e5, CRS) is None   # off the DEM


def test_opensfm_topocentric_frame_is_converted_into_utm(tmp_path):
    """An OpenSfM reconstruction (topocentric frame, which a GeoTIFF cannot record) comes out in the WGS 84 UTM
    zone of its centre: zone 33 N at lon 15 deg; the block's geometry is kept (baselines to 0.25 m over 50-110 m:
    the poses' own 5 cm noise per axis, 7 cm on a difference, and the projection's scale 0.9996)."""
    images, poses, _ = write_example_block(tmp_path)
    write_example_reconstruction(tmp_path, images, poses)
    so = load_orientation(tmp_path / "reconstruction.json")
    assert so.orientation.crs == "EPSG:32633" and TOPOCENTRIC_METHOD in (so.converted_from or "")
    got = np.array([p.position for p in so.orientation.poses])
    want = np.array([p.position for p in poses])
    np.testing.assert_allclose(got - got[0], want - want[0], atol=0.25)
    assert "converted from topocentric" in so.orientation.frame
