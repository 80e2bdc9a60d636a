"""Camera files (--camera FILE): ROS camera_calibration YAML, TOML and JSON."""

from __future__ import annotations

import json
import re
import shutil
import sys

import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.camera_file import load_camera_file
from covo_gtsam.cli import main
from covo_gtsam.errors import ConfigError
from covo_gtsam.io import load_tum_trajectory

FR1 = {"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3, "k1": 0.2624, "k2": -0.9531, "p1": -0.0054,
       "p2": 0.0026, "k3": 1.1633, "width": 640, "height": 480, "depth_scale": 5000}

FR1_YAML = """\
image_width: 640
image_height: 480
camera_name: kinect_fr1
camera_matrix:
  rows: 3
  cols: 3
  data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [517.3, 0, 318.6, 0, 0, 516.5, 255.3, 0, 0, 0, 1, 0]
"""


def _same_camera(cam: Camera, ref: Camera) -> None:
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.dist, cam.width, cam.height) == (
        ref.fx, ref.fy, ref.cx, ref.cy, ref.dist, ref.width, ref.height)


def test_json_toml_yaml_read_the_published_fr1_values(tmp_path):
    fr1 = Camera.preset("fr1")
    (tmp_path / "c.json").write_text(json.dumps(FR1))
    cam, scale = load_camera_file(tmp_path / "c.json")
    _same_camera(cam, fr1)
    assert scale == 5000
    (tmp_path / "c.yaml").write_text(FR1_YAML)
    pytest.importorskip("yaml")
    cam, scale = load_camera_file(tmp_path / "c.yaml")
    _same_camera(cam, fr1)
    assert scale is None and cam.name == "kinect_fr1"
    if sys.version_info >= (3, 11):
        (tmp_path / "c.toml").write_text("".join(f"{k} = {v}\n" for k, v in {**FR1, "depth_scale": 1000}.items()))
        cam, scale = load_camera_file(tmp_path / "c.toml")
        _same_camera(cam, fr1)
        assert scale == 1000


def test_camera_file_gives_the_trajectory_of_the_fr1_preset(sample_dir, tmp_path, capsys):
    # a folder whose name names no camera: the preset is not guessed, the file says it all
    seq = tmp_path / "some_other_dataset"
    shutil.copytree(sample_dir, seq)
    (tmp_path / "fr1.json").write_text(json.dumps(FR1))
    assert main(["run", str(seq), "--out", str(tmp_path / "preset"), "--camera", "fr1", "--max-frames", "12",
                 "--no-plots", "--quiet"]) == 0
    assert main(["run", str(seq), "--out", str(tmp_path / "file"), "--camera", str(tmp_path / "fr1.json"),
                 "--max-frames", "12", "--no-plots", "--quiet"]) == 0
    t0, P0 = load_tum_trajectory(tmp_path / "preset" / "trajectory.txt")
    t1, P1 = load_tum_trajectory(tmp_path / "file" / "trajectory.txt")
    assert len(t0) >= 10
    np.testing.assert_array_equal(t0, t1)
    np.testing.assert_allclose(P1, P0, atol=1e-9)
    # without --camera the folder stays a clear error
    capsys.readouterr()
    assert main(["run", str(seq), "--out", str(tmp_path / "none"), "--max-frames", "5", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--camera" in err


def test_camera_file_depth_scale_reaches_the_run(sample_dir, tmp_path):
    """depth_scale 2500 doubles every depth: the trajectory's translation doubles, the rotation stays."""
    seq = tmp_path / "other"
    shutil.copytree(sample_dir, seq)
    (tmp_path / "a.json").write_text(json.dumps(FR1))
    (tmp_path / "b.json").write_text(json.dumps({**FR1, "depth_scale": 2500}))
    for name in ("a", "b"):
        assert main(["run", str(seq), "--out", str(tmp_path / name), "--camera", str(tmp_path / f"{name}.json"),
                     "--max-frames", "8", "--no-plots", "--quiet"]) == 0
    _, Pa = load_tum_trajectory(tmp_path / "a" / "trajectory.txt")
    _, Pb = load_tum_trajectory(tmp_path / "b" / "trajectory.txt")
    assert len(Pa) == len(Pb) >= 6
    moved = np.linalg.norm(Pa[-1, :3, 3])
    assert moved > 1e-3
    assert np.linalg.norm(Pb[-1, :3, 3]) / moved == pytest.approx(2.0, rel=0.2)


@pytest.mark.parametrize("content, needle", [
    ({k: v for k, v in FR1.items() if k not in ("fx", "depth_scale")}, "missing keys fx, depth_scale"),
    ({**FR1, "fz": 1.0}, "unknown keys fz"),
    ({**{k: v for k, v in FR1.items() if k != "fx"}, "fxx": FR1["fx"]}, "unknown keys fxx"),  # and fx missing
    ({**FR1, "fx": "big"}, "fx must be a finite number"),
    ({**FR1, "width": 640.5}, "width must be a positive integer"),
    ({**FR1, "fx": -1.0}, "focal lengths must be positive"),
    ({**FR1, "fx": 1e-200}, "focal lengths must be 1 to 1e"),
    ({**FR1, "fy": 1e200}, "focal lengths must be 1 to 1e"),
])
def test_bad_camera_file_is_one_line_exit_2(sample_dir, tmp_path, capsys, content, needle):
    f = tmp_path / "cam.json"
    f.write_text(json.dumps(content))
    with pytest.raises(ConfigError, match=needle):
        load_camera_file(f)
    assert main(["run", str(sample_dir), "--out", str(tmp_path / "o"), "--camera", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and str(f) in err


def test_yaml_missing_keys_and_unknown_camera(tmp_path, capsys, sample_dir):
    pytest.importorskip("yaml")
    f = tmp_path / "cam.yaml"
    f.write_text(FR1_YAML.replace("image_width: 640\n", ""))
    with pytest.raises(ConfigError, match=r"missing keys image_width \(ROS camera_calibration YAML\)$"):
        load_camera_file(f)
    f.write_text(FR1_YAML.replace("image_width: 640\n", "image_widht: 640\n"))
    with pytest.raises(ConfigError, match="missing keys image_width .*; unknown keys image_widht"):
        load_camera_file(f)
    assert main(["run", str(sample_dir), "--out", str(tmp_path / "o"), "--camera", "fr9", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fr9" in err


@pytest.mark.parametrize("content, needle", [
    ({**FR1, "cx": 5000}, "principal point cx=5000 px is outside the image (0 to 640 px)"),
    ({**FR1, "cy": -3000}, "principal point cy=-3000 px is outside the image (0 to 480 px)"),
    ({**FR1, "k1": 1e6, "k3": -1e9}, "cannot be undistorted over the 640x480 image"),
], ids=["cx", "cy", "distortion"])
def test_principal_point_and_distortion_that_do_not_fit_the_image_are_rejected(tmp_path, content, needle):
    f = tmp_path / "cam.json"
    f.write_text(json.dumps(content))
    with pytest.raises(ConfigError, match=re.escape(needle)):
        load_camera_file(f)


def test_principal_point_on_the_image_border_and_real_distortions_load(tmp_path):
    no_dist = {k: v for k, v in FR1.items() if k not in ("k1", "k2", "p1", "p2", "k3")}
    for cx, cy in ((0, 0), (640, 480)):
        (tmp_path / "c.json").write_text(json.dumps({**no_dist, "cx": cx, "cy": cy}))
        cam, _ = load_camera_file(tmp_path / "c.json")
        assert (cam.cx, cam.cy) == (cx, cy)
    opencv_tutorial = {"fx": 532.795, "fy": 532.919, "cx": 342.458, "cy": 233.901, "k1": -0.281086,
                       "k2": 0.0272581, "p1": 0.00121666, "p2": -0.000134204, "k3": 0.158514}
    fr2 = Camera.preset("fr2")
    fr2_values = dict(zip(("fx", "fy", "cx", "cy"), (fr2.fx, fr2.fy, fr2.cx, fr2.cy)))
    for values in (opencv_tutorial, {**fr2_values, **dict(zip(("k1", "k2", "p1", "p2", "k3"), fr2.dist))}):
        (tmp_path / "c.json").write_text(json.dumps({**FR1, **values}))
        assert load_camera_file(tmp_path / "c.json")[0].dist == tuple(values[k] for k in ("k1", "k2", "p1", "p2", "k3"))


@pytest.mark.parametrize("f, k1, k2, size", [(300, -0.3, 0.1, (640, 480)), (250, -0.4, 0.15, (640, 480)),
                                             (191, -0.23, 0.05, (512, 512))])
def test_wide_angle_distortions_that_do_not_fold_load_and_undistort(tmp_path, f, k1, k2, size):
    """r - 0.3 r^3 + 0.1 r^5 and the like grow monotonically over the image: invertible, though the
    fixed-point undistortion needs more than its first 20 steps at the corners. OpenCV 4's fixed
    point (4.8, the floor version) stalls short of the preimage there (45 px off at the corner of the
    first camera), so with it such a camera is refused with the clear error, never undistorted wrongly."""
    import cv2

    w, h = size
    values = {"fx": f, "fy": f, "cx": w / 2, "cy": h / 2, "width": w, "height": h, "depth_scale": 5000,
              "k1": k1, "k2": k2, "p1": 0.0, "p2": 0.0, "k3": 0.0}
    (tmp_path / "c.json").write_text(json.dumps(values))
    if int(cv2.__version__.split(".")[0]) < 5:
        with pytest.raises(ConfigError, match="cannot be undistorted"):
            load_camera_file(tmp_path / "c.json")
    else:
        cam, _ = load_camera_file(tmp_path / "c.json")
        u, v = np.meshgrid(np.arange(0.0, w + 1, 4), np.arange(0.0, h + 1, 4))
        uv = np.stack([u.ravel(), v.ravel()], axis=1)
        assert np.abs(cam.distort(cam.undistort(uv)) - uv).max() <= 0.01
    folded = {**values, "fx": 400, "fy": 400, "k1": -0.4, "k2": 0.0}  # the corners have no preimage
    (tmp_path / "c.json").write_text(json.dumps(folded))
    with pytest.raises(ConfigError, match="cannot be undistorted"):
        load_camera_file(tmp_path / "c.json")



def _yaml_with(camera_matrix: str = "", distortion: str = "") -> str:
    text = FR1_YAML
    if camera_matrix:
        text = text.replace("  rows: 3\n  cols: 3\n  data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]\n",
                            camera_matrix, 1)
    if distortion:
        text = text.replace("  rows: 1\n  cols: 5\n  data: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]\n", distortion)
    return text


@pytest.mark.parametrize("camera_matrix, distortion, needle", [
    ("  rows: 3\n  cols: 3\n  data: [517.3, 0.5, 318.6, 0, 516.5, 255.3, 0, 0, 1]\n", "",
     "camera_matrix skew (data[1]) must be 0, got 0.5"),
    ("  rows: 3\n  cols: 3\n  data: [517.3, 0, 0, 0, 516.5, 0, 318.6, 255.3, 1]\n", "",
     "camera_matrix third row must be [0, 0, 1], got [318.6, 255.3, 1] (a transposed, column-major matrix?)"),
    ("  rows: 3\n  cols: 3\n  data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 2]\n", "",
     "camera_matrix third row must be [0, 0, 1], got [0, 0, 2]"),
    ("  rows: 3\n  cols: 3\n  data: [517.3, 0, 318.6, 0.1, 516.5, 255.3, 0, 0, 1]\n", "",
     "camera_matrix data[3] (row 2, column 1) must be 0, got 0.1"),
    ("  rows: 2\n  cols: 2\n  data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]\n", "",
     "camera_matrix has rows: 2, cols: 2 but 9 data values"),
    ("  rows: 1\n  cols: 9\n  data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]\n", "",
     "camera_matrix must be 3x3, got rows: 1, cols: 9"),
    ("", "  rows: 1\n  cols: 4\n  data: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]\n",
     "distortion_coefficients has rows: 1, cols: 4 but 5 data values"),
    ("", "  data: [0.2624, abc, -0.0054, 0.0026, 1.1633]\n", "distortion_coefficients.data must be a finite number, "
     "got 'abc'"),
    ("", "  data: [0.2624, nan, -0.0054, 0.0026, 1.1633]\n", "got 'nan'"),
    ("", "  data: [0.2624, .nan, -0.0054, 0.0026, 1.1633]\n", "got nan"),
    ("", "  data: [0.2624, 1e999, -0.0054, 0.0026, 1.1633]\n", "got '1e999'"),
], ids=["skew", "transposed", "third-row", "lower-left", "rows-cols", "shape", "distortion-cols", "text",
        "nan-text", "nan", "overflow"])
def test_yaml_camera_matrix_and_matrix_sizes_are_checked(tmp_path, camera_matrix, distortion, needle):
    pytest.importorskip("yaml")
    f = tmp_path / "cam.yaml"
    f.write_text(_yaml_with(camera_matrix, distortion))
    with pytest.raises(ConfigError, match=re.escape(needle)):
        load_camera_file(f)


def test_ros_yaml_numbers_in_scientific_notation_read_as_numbers(tmp_path):
    """YAML 1.1 (PyYAML) reads 5.173E2 and 2624e-4 as strings; ROS's reader takes them as numbers."""
    yaml = pytest.importorskip("yaml")
    text = _yaml_with("  rows: 3\n  cols: 3\n  data: [5.173E2, 0., 3.186e+02, 0., 5.165E2, 2553e-1, 0., 0., 1.]\n",
                      "  rows: 1\n  cols: 5\n  data: [2624e-4, -9.531E-1, -5.4e-03, 26E-4, 1.1633E0]\n")
    text += "depth_scale: 5e3\n"
    assert isinstance(yaml.safe_load(text)["camera_matrix"]["data"][0], str)
    f = tmp_path / "cam.yaml"
    f.write_text(text)
    cam, scale = load_camera_file(f)
    _same_camera(cam, Camera.preset("fr1"))
    assert scale == 5000.0


def _opencv_calibration(path, K=None, D=None, extra: dict | None = None, skip=()):
    """A calibration file written by OpenCV's own ``cv2.FileStorage``, laid out as OpenCV's camera
    calibration sample writes it (with its entries covo does not use)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Wed Nov 25 12:00:00 2026")
    fs.write("nr_of_frames", 25)
    for k, v in (("image_width", 640), ("image_height", 480)):
        if k not in skip:
            fs.write(k, v)
    fs.write("board_width", 9)
    fs.write("flags", 0)
    if "camera_matrix" not in skip:
        fs.write("camera_matrix", np.array([[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]]) if K is None else K)
    fs.write("distortion_coefficients", np.array([[FR1[k]] for k in ("k1", "k2", "p1", "p2", "k3")])
             if D is None else D)
    fs.write("avg_reprojection_error", 0.21)
    fs.write("per_view_reprojection_errors", np.full((25, 1), 0.2))
    for k, v in (extra or {}).items():
        fs.write(k, v)
    fs.release()
    return path


def test_opencv_calibration_file_reads_the_fr1_values(sample_dir, tmp_path):
    f = _opencv_calibration(tmp_path / "calib.yml")
    assert "!!opencv-matrix" in f.read_text()  # the dialect PyYAML cannot read
    cam, scale = load_camera_file(f)
    _same_camera(cam, Camera.preset("fr1"))
    assert scale is None
    g = _opencv_calibration(tmp_path / "calib_mm.yaml", extra={"depth_scale": 1000.0})
    assert load_camera_file(g)[1] == 1000.0
    # and the run gives the preset's trajectory
    seq = tmp_path / "some_other_dataset"
    shutil.copytree(sample_dir, seq)
    for name, camera in (("preset", "fr1"), ("file", str(f))):
        assert main(["run", str(seq), "--out", str(tmp_path / name), "--camera", camera, "--max-frames", "8",
                     "--no-plots", "--quiet"]) == 0
    t0, P0 = load_tum_trajectory(tmp_path / "preset" / "trajectory.txt")
    t1, P1 = load_tum_trajectory(tmp_path / "file" / "trajectory.txt")
    assert len(t0) >= 6
    np.testing.assert_array_equal(t0, t1)
    np.testing.assert_allclose(P1, P0, atol=1e-9)


@pytest.mark.parametrize("kwargs, needle", [
    (dict(skip=("camera_matrix",)), "missing keys camera_matrix (OpenCV calibration file)"),
    (dict(skip=("image_width",)), "missing keys image_width (OpenCV calibration file)"),
    (dict(K=np.array([[517.3, 0, 318.6], [0, 516.5, 255.3]])), "camera_matrix must be 3x3, got 2x3"),
    (dict(K=np.array([[517.3, 2.0, 318.6], [0, 516.5, 255.3], [0, 0, 1]])), "skew"),
    (dict(K=np.array([[517.3, 0, 0], [0, 516.5, 0], [318.6, 255.3, 1]])), "transposed"),
    (dict(D=np.array([[0.1], [0.0], [0.0], [0.0], [0.0], [0.3], [0.0], [0.0]])), "k4..k6 are not supported"),
    (dict(D=np.zeros((3, 1))), "distortion_coefficients needs 4, 5 or 8 numbers, got 3"),
    (dict(extra={"fisheye_model": 1}), "fisheye_model is not supported"),
    (dict(extra={"image_width": 640.5}), "image_width must be a positive integer"),
])
def test_bad_opencv_calibration_file_is_one_line_exit_2(sample_dir, tmp_path, capsys, kwargs, needle):
    skip = kwargs.pop("skip", ())
    extra = kwargs.get("extra", {})
    if "image_width" in extra:
        skip = ("image_width",)
    f = _opencv_calibration(tmp_path / "cam.yaml", skip=skip, **kwargs)
    with pytest.raises(ConfigError, match=re.escape(needle)):
        load_camera_file(f)
    assert main(["run", str(sample_dir), "--out", str(tmp_path / "o"), "--camera", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and str(f) in err


def test_broken_opencv_calibration_file_is_a_clear_error(tmp_path):
    f = tmp_path / "cam.yaml"
    f.write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: [\n")
    with pytest.raises(ConfigError, match="not a valid OpenCV calibration file"):
        load_camera_file(f)
