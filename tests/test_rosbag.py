"""ROS bags in and out. Bags are built from the shared TUM frames with rosbags' writer and read back
with rosbags' reader; the output covariances are checked by sampling, not by a formula."""

from __future__ import annotations

import json
import shutil
from decimal import Decimal
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from covo_gtsam.cli import main  # noqa: E402
from covo_gtsam.datasets.images import load_depth  # noqa: E402
from covo_gtsam.datasets.rosbag import RosbagSequence  # noqa: E402
from covo_gtsam.datasets.tum import TumSequence  # noqa: E402
from covo_gtsam.errors import DatasetError  # noqa: E402
from covo_gtsam.io import load_relative_poses, load_tum_trajectory  # noqa: E402
from covo_gtsam.ros_io import UNKNOWN_TWIST_VARIANCE  # noqa: E402

N = 20
FRAME = "openni_rgb_optical_frame"
FR1_K = [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]
FR1_D = [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]


def _typestore(ros1: bool):
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
    return ts


def _header(ts, ros1, t, frame_id):
    ns = int(round(t * 1e6)) * 1000  # the text files' whole microseconds, which a float in seconds cannot hold
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    H = ts.types["std_msgs/msg/Header"]
    return H(seq=0, stamp=stamp, frame_id=frame_id) if ros1 else H(stamp=stamp, frame_id=frame_id)


def _image(ts, ros1, t, arr, encoding):
    arr = np.ascontiguousarray(arr)
    h, w = arr.shape[:2]
    return ts.types["sensor_msgs/msg/Image"](
        header=_header(ts, ros1, t, FRAME), height=h, width=w, encoding=encoding, is_bigendian=0,
        step=arr.nbytes // h, data=arr.view(np.uint8).reshape(-1))


def write_bag(path, seq: TumSequence, ros1: bool, colour: str, depth: str, n: int = N, tf: bool = True,
              info: bool = True, topics=("/camera/rgb/image_color", "/camera/depth/image"), mcap: bool = False,
              chain: bool = False, info_fields: dict | None = None):
    """A bag of the first ``n`` frames of ``seq``: colour rgb8/bgr8, depth 32FC1 (metres, NaN = none)
    or 16UC1 (millimetres, rounded), fr1 camera info (``info_fields`` replaces some of its fields,
    ROS 1 names: ``K``, ``D``, ``width``, ...), /tf world -> camera from groundtruth.txt
    (with ``chain``, like the TUM bags: world -> kinect moving, kinect -> openni_rgb_frame ->
    camera fixed, all on /tf at the ground-truth rate)."""
    ts = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
        writer, ser = Writer(path, version=8, storage_plugin=plugin), ts.serialize_cdr
    writer.open()
    img_t = "sensor_msgs/msg/Image"
    c_rgb = writer.add_connection(topics[0], img_t, typestore=ts)
    c_dep = writer.add_connection(topics[1], img_t, typestore=ts)
    msgs = []
    for i in range(n):
        t = float(seq.timestamps[i])
        bgr = cv2.imread(seq.rgb_paths[i], cv2.IMREAD_COLOR)
        col = bgr[:, :, ::-1] if colour == "rgb8" else bgr
        msgs.append((t, c_rgb, ser(_image(ts, ros1, t, col, colour), img_t)))
        # the depth image's own stamp, from depth.txt via the file name
        td = float(seq.depth_paths[i].rsplit("/", 1)[1][:-4])
        if depth == "32FC1":
            d = load_depth(seq.depth_paths[i], 5000.0)
            d = np.where(d > 0, d, np.float32(np.nan)).astype("<f4")
        elif depth == "16UC1":
            raw = cv2.imread(seq.depth_paths[i], cv2.IMREAD_UNCHANGED)
            d = np.round(raw / 5.0).astype("<u2")
        else:  # an unsupported encoding
            d = load_depth(seq.depth_paths[i], 5000.0).astype("<f8")
        msgs.append((td, c_dep, ser(_image(ts, ros1, td, d, depth), img_t)))
    if info:
        info_t = "sensor_msgs/msg/CameraInfo"
        c_info = writer.add_connection("/camera/rgb/camera_info", info_t, typestore=ts)
        CI = ts.types[info_t]
        kw = dict(header=_header(ts, ros1, float(seq.timestamps[0]), FRAME), height=480, width=640,
                  distortion_model="plumb_bob", binning_x=0, binning_y=0,
                  roi=ts.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                   do_rectify=False))
        mats = dict(D=np.array(FR1_D), K=np.array(FR1_K, float), R=np.eye(3).reshape(-1),
                    P=np.array([517.3, 0, 318.6, 0, 0, 516.5, 255.3, 0, 0, 0, 1, 0], float))
        for k, v in (info_fields or {}).items():
            if k in mats:
                mats[k] = np.array(v, float)
            else:
                kw[k] = v
        kw.update(mats if ros1 else {k.lower(): v for k, v in mats.items()})
        msgs.append((float(seq.timestamps[0]) - 0.001, c_info, ser(CI(**kw), info_t)))
    if tf:
        from covo_gtsam.io import load_tum_trajectory as load_gt

        gt_t, gt_P = load_gt(seq.path / "groundtruth.txt")
        keep = (gt_t > seq.timestamps[0] - 0.2) & (gt_t < seq.timestamps[n - 1] + 0.2)
        tf_t = "tf2_msgs/msg/TFMessage"
        c_tf = writer.add_connection("/tf", tf_t, typestore=ts)
        T = ts.types
        from covo_gtsam.geometry import matrix_to_quat

        def transform(t, parent, child, P):
            q = matrix_to_quat(P[:3, :3])
            return T["geometry_msgs/msg/TransformStamped"](
                header=_header(ts, ros1, float(t), parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=P[0, 3], y=P[1, 3], z=P[2, 3]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))

        # fixed links: kinect -> rgb frame (a shift), rgb frame -> optical frame (the usual rotation)
        T_kr = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, -0.02, 0.0])).matrix()
        T_ro = gtsam.Pose3(gtsam.Rot3.RzRyRx(-np.pi / 2, 0, -np.pi / 2), np.zeros(3)).matrix()
        for t, P in zip(gt_t[keep], gt_P[keep]):
            if chain:
                trs = [transform(t, "/world", "/kinect", P @ np.linalg.inv(T_kr @ T_ro)),
                       transform(t, "/kinect", "/openni_rgb_frame", T_kr),
                       transform(t, "/openni_rgb_frame", "/" + FRAME, T_ro)]
            else:
                trs = [transform(t, "/world", FRAME, P)]
            msgs.append((float(t), c_tf, ser(T[tf_t](transforms=trs), tf_t)))
    for t, conn, data in sorted(msgs, key=lambda m: m[0]):
        writer.write(conn, int(round(t * 1e9)), data)
    writer.close()
    return path


def reference_folder(dst, seq: TumSequence, n: int = N, millimetres: bool = False):
    """A TUM folder of the same pixels: grey PNGs converted like the bag reader (cvtColor) and the
    depth PNGs as they are, or rounded to millimetres."""
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for i in range(n):
        rname = seq.rgb_paths[i].rsplit("/", 1)[1]
        dname = seq.depth_paths[i].rsplit("/", 1)[1]
        grey = cv2.cvtColor(cv2.imread(seq.rgb_paths[i], cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
        cv2.imwrite(str(dst / "rgb" / rname), grey)
        raw = cv2.imread(seq.depth_paths[i], cv2.IMREAD_UNCHANGED)
        if millimetres:
            raw = np.round(raw / 5.0).astype(np.uint16)
        cv2.imwrite(str(dst / "depth" / dname), raw)
        rgb_lines.append(f"{rname[:-4]} rgb/{rname}\n")
        depth_lines.append(f"{dname[:-4]} depth/{dname}\n")
    (dst / "rgb.txt").write_text("".join(rgb_lines))
    (dst / "depth.txt").write_text("".join(depth_lines))
    shutil.copy(seq.path / "groundtruth.txt", dst / "groundtruth.txt")
    return dst


def _run(args):
    assert main(args + ["--no-plots", "--quiet"]) == 0


def _same_trajectory(a, b):
    ta, Pa = load_tum_trajectory(a / "trajectory.txt")
    tb, Pb = load_tum_trajectory(b / "trajectory.txt")
    assert len(ta) >= N - 2
    np.testing.assert_allclose(tb, ta, atol=1e-6)
    np.testing.assert_allclose(Pb[:, :3, 3], Pa[:, :3, 3], atol=1e-6)
    for A, B in zip(Pa, Pb):  # rotation difference angle
        assert np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(A[:3, :3].T @ B[:3, :3]))) < 1e-6


@pytest.mark.slow
@pytest.mark.realdata
def test_ros1_bag_rgb8_32fc1_runs_like_the_folder(fr1_rpy_dir, tmp_path, capsys):
    seq = TumSequence(fr1_rpy_dir)
    bag = write_bag(tmp_path / "fr1.bag", seq, ros1=True, colour="rgb8", depth="32FC1", chain=True)
    ref = reference_folder(tmp_path / "rgbd_dataset_freiburg1_ref", seq)
    # the tf chain world -> kinect -> rgb frame -> optical frame gives groundtruth.txt's poses
    rs = RosbagSequence(bag)
    assert rs.gt_valid.all()
    np.testing.assert_allclose(rs.groundtruth, seq.groundtruth[:N], atol=1e-6)
    # the chain's samples are groundtruth.txt's own within the bag's span (the moving link's stamps,
    # the fixed links composed in): the reference's jitter is measured from them as from the file
    stamps, poses = seq.gt_samples
    span = (stamps > seq.timestamps[0] - 0.2) & (stamps < seq.timestamps[N - 1] + 0.2)
    np.testing.assert_allclose(rs.gt_samples[0], stamps[span], atol=1e-6)
    np.testing.assert_allclose(rs.gt_samples[1], poses[span], atol=1e-6)
    # the colour-depth offsets the run uses come from the depth messages' own stamps, as from depth.txt
    # (tens of microseconds in these frames: a bag without them would fail this)
    np.testing.assert_allclose(rs.depth_timestamps - rs.timestamps, seq.depth_timestamps[:N] - seq.timestamps[:N],
                               atol=1e-6)
    _run(["run", str(bag), "--out", str(tmp_path / "bag_out"), "--bag-out", "ros1"])
    _run(["run", str(ref), "--out", str(tmp_path / "ref_out")])
    _same_trajectory(tmp_path / "ref_out", tmp_path / "bag_out")
    # ground truth from /tf gives the folder's metrics
    mb = json.loads((tmp_path / "bag_out" / "metrics.json").read_text())
    mr = json.loads((tmp_path / "ref_out" / "metrics.json").read_text())
    assert mb["rpe_1"]["trans_rmse"] == pytest.approx(mr["rpe_1"]["trans_rmse"], rel=1e-4)
    assert mb["anees_translation"] == pytest.approx(mr["anees_translation"], rel=1e-3)
    assert mb["nees_with_reference_jitter"] and mb["reference_jitter"]["samples"] > 0
    check_output_bag(tmp_path / "bag_out", tmp_path / "bag_out" / "odometry.bag", FRAME, input_bag=bag)


@pytest.mark.slow
@pytest.mark.realdata
def test_ros2_bag_bgr8_16uc1_runs_like_the_millimetre_folder(fr1_rpy_dir, tmp_path, capsys):
    seq = TumSequence(fr1_rpy_dir)
    bag = write_bag(tmp_path / "fr1_ros2", seq, ros1=False, colour="bgr8", depth="16UC1", tf=False)
    ref = reference_folder(tmp_path / "ref", seq, millimetres=True)
    cam = tmp_path / "fr1_mm.json"
    cam.write_text(json.dumps({"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3, "k1": FR1_D[0], "k2": FR1_D[1],
                               "p1": FR1_D[2], "p2": FR1_D[3], "k3": FR1_D[4], "width": 640, "height": 480,
                               "depth_scale": 1000}))
    capsys.readouterr()
    _run(["run", str(bag), "--out", str(tmp_path / "bag_out"), "--bag-out", "ros2"])
    assert "no ground truth" in capsys.readouterr().out
    _run(["run", str(ref), "--out", str(tmp_path / "ref_out"), "--camera", str(cam)])
    _same_trajectory(tmp_path / "ref_out", tmp_path / "bag_out")
    m = json.loads((tmp_path / "bag_out" / "metrics.json").read_text())
    assert m["rpe_1"] is None and m["not_computed"]["rpe_1"] == "the sequence has no ground truth"
    check_output_bag(tmp_path / "bag_out", tmp_path / "bag_out" / "odometry", FRAME, input_bag=bag)


def _ros_errors(T: gtsam.Pose3, samples):
    """Position error and fixed-axis small rotation of sampled poses, ROS order [trans, rot]."""
    R_inv = T.rotation().inverse()
    return np.array([np.concatenate([S.translation() - T.translation(),
                                     gtsam.Rot3.Logmap(S.rotation().compose(R_inv))]) for S in samples])


def _whitened_eigs(C, emp):
    Li = np.linalg.inv(np.linalg.cholesky(C))
    return np.linalg.eigvalsh(Li @ emp @ Li.T)


def _pose(msg_pose):
    p, q = msg_pose.position, msg_pose.orientation
    return gtsam.Pose3(gtsam.Rot3.Quaternion(q.w, q.x, q.y, q.z), np.array([p.x, p.y, p.z]))


def _colour_stamps(bag_path, topic="/camera/rgb/image_color"):
    """The (sec, nanosec) stamps of a bag's colour images, read with rosbags."""
    with AnyReader([Path(bag_path)]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(m.header.stamp.sec, m.header.stamp.nanosec)
                for m in (reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns))]


def check_output_bag(out, bag_path, camera_frame, input_bag=None):
    """Read the written bag back with rosbags; poses equal the text files; covariances equal the
    empirical covariance of sampled position errors and fixed-axis rotations; with ``input_bag``,
    the messages carry the input colour images' stamps exactly, to the nanosecond."""
    stamps, traj = load_tum_trajectory(out / "trajectory.txt")
    t_ref, t_cur, rel, covs = load_relative_poses(out / "relative.txt")
    odom, relm = [], []
    with AnyReader([bag_path]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics == {"/covo/odometry": "nav_msgs/msg/Odometry",
                          "/covo/relative": "geometry_msgs/msg/PoseWithCovarianceStamped"}
        for conn, ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            (odom if conn.topic == "/covo/odometry" else relm).append((ns, msg))
    assert len(odom) == len(stamps) and len(relm) == len(t_cur) >= N - 3
    for (ns, m), t, P in zip(odom, stamps, traj):
        assert m.header.frame_id == "odom" and m.child_frame_id == camera_frame
        assert abs(ns * 1e-9 - t) < 1e-6
        np.testing.assert_allclose(_pose(m.pose.pose).matrix(), P, atol=1e-8)
    for (_, m), a, _, T in zip(relm, t_ref, t_cur, rel):
        assert m.header.frame_id == f"{camera_frame}@{a:.6f}"
        np.testing.assert_allclose(_pose(m.pose.pose).matrix(), T, atol=1e-8)
    if input_bag is not None:
        # exact stamps pair covo's messages with the images (message_filters' ExactTime, a dict
        # keyed by stamp); seconds as a float would miss most by up to a tenth of a microsecond
        colour = _colour_stamps(input_bag)
        out_stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for _, m in odom]
        assert out_stamps == colour[:len(out_stamps)]
        assert [(m.header.stamp.sec, m.header.stamp.nanosec) for _, m in relm] == out_stamps[1:len(relm) + 1]
        assert [ns for ns, _ in odom] == [s * 10**9 + n for s, n in out_stamps]
    # the first frame has no pair: a zero twist that a filter must not trust (not a zero covariance)
    first = np.array(odom[0][1].twist.covariance).reshape(6, 6)
    np.testing.assert_array_equal(first, UNKNOWN_TWIST_VARIANCE * np.eye(6))

    rng = np.random.default_rng(0)
    # relative pose: sample T_true = T Exp(xi), xi ~ N(0, relative.txt's covariance)
    k = int(np.argmax(np.linalg.norm(rel[:, :3, 3], axis=1)))
    T = gtsam.Pose3(rel[k])
    L = np.linalg.cholesky(covs[k])
    draws = [T.compose(gtsam.Pose3.Expmap(L @ rng.standard_normal(6))) for _ in range(20000)]
    e = _ros_errors(T, draws)
    C = np.array(relm[k][1].pose.covariance).reshape(6, 6)
    eig = _whitened_eigs(C, e.T @ e / len(e))
    assert np.all(np.abs(eig - 1) < 0.06), eig

    # odometry pose of the last frame: compose the sampled relative poses along the chain
    chol = [np.linalg.cholesky(c) for c in covs]
    n_draws = 3000
    last = float(t_cur[-1])
    samples = []
    for _ in range(n_draws):
        world = {float(stamps[0]): gtsam.Pose3()}
        for a, b, Tk, Lk in zip(t_ref, t_cur, rel, chol):
            world[float(b)] = world[float(a)].compose(gtsam.Pose3(Tk)).compose(
                gtsam.Pose3.Expmap(Lk @ rng.standard_normal(6)))
        samples.append(world[last])
    T_last = gtsam.Pose3(traj[-1])
    e = _ros_errors(T_last, samples)
    C = np.array(odom[-1][1].pose.covariance).reshape(6, 6)
    eig = _whitened_eigs(C, e.T @ e / n_draws)
    assert np.all(np.abs(eig - 1) < 0.15), eig

    # twist: mean body twist over the last pair
    m = odom[-1][1]
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(rel[-1])) / (t_cur[-1] - t_ref[-1])
    tw = m.twist.twist
    np.testing.assert_allclose([tw.angular.x, tw.angular.y, tw.angular.z], xi[:3], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose([tw.linear.x, tw.linear.y, tw.linear.z], xi[3:], rtol=1e-6, atol=1e-9)
    # its covariance: sampled twists Log(T_ref,cur Exp(xi)) / dt, ROS order [linear, angular]
    dt = t_cur[-1] - t_ref[-1]
    T = gtsam.Pose3(rel[-1])
    L = np.linalg.cholesky(covs[-1])
    tw_s = np.array([gtsam.Pose3.Logmap(T.compose(gtsam.Pose3.Expmap(L @ rng.standard_normal(6)))) / dt
                     for _ in range(20000)])
    tw_s = np.concatenate([tw_s[:, 3:], tw_s[:, :3]], axis=1)
    tw_s -= tw_s.mean(axis=0)
    C = np.array(m.twist.covariance).reshape(6, 6)
    eig = _whitened_eigs(C, tw_s.T @ tw_s / len(tw_s))
    assert np.all(np.abs(eig - 1) < 0.06), eig


@pytest.mark.realdata
def test_bag_bad_input_is_one_line_exit_2(fr1_desk_dir, tmp_path, capsys):
    seq = TumSequence(fr1_desk_dir)
    no_topics = write_bag(tmp_path / "other.bag", seq, ros1=True, colour="rgb8", depth="32FC1", n=3, tf=False,
                          topics=("/cam/color", "/cam/depth"))
    wrong = write_bag(tmp_path / "wrong", seq, ros1=False, colour="bgr8", depth="64FC1", n=3, tf=False)
    capsys.readouterr()
    assert main(["run", str(no_topics), "--out", str(tmp_path / "o1"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/camera/rgb/image_color" in err and "/cam/color" in err
    assert main(["run", str(wrong), "--out", str(tmp_path / "o2"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/camera/depth/image" in err and "64FC1" in err
    # the topic options pick other names
    assert main(["run", str(no_topics), "--out", str(tmp_path / "o3"), "--rgb-topic", "/cam/color",
                 "--depth-topic", "/cam/depth", "--no-plots", "--quiet"]) == 0
    assert len(load_tum_trajectory(tmp_path / "o3" / "trajectory.txt")[0]) == 3
    # a bag is accepted by run only
    assert main(["analyze-noise", str(no_topics), "--out", str(tmp_path / "o4"), "--quiet"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("ros1, fields, needle", [
    (True, {"K": [517.3, 0, 700.0, 0, 516.5, 255.3, 0, 0, 1]},
     "principal point cx=700 px is outside the image (0 to 640 px)"),
    (False, {"K": [517.3, 0.5, 318.6, 0, 516.5, 255.3, 0, 0, 1]}, "K skew (K[1]) must be 0, got 0.5"),
    (True, {"K": [517.3, 0, 0, 0, 516.5, 0, 318.6, 255.3, 1]},
     "K third row must be [0, 0, 1], got [318.6, 255.3, 1] (a transposed, column-major matrix?)"),
    (False, {"K": [0.5, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]}, "camera focal lengths must be 1 to 1e+06 px"),
    (True, {"D": [1e6, 0, 0, 0, -1e9]}, "cannot be undistorted over the 640x480 image"),
    (False, {"height": 0}, "height must be a positive integer, got 0"),
], ids=["principal-point", "skew", "transposed", "focal-length", "distortion", "size"])
def test_bag_camera_info_gets_the_checks_of_a_camera_file(sample_dir, tmp_path, capsys, ros1, fields, needle):
    import re

    bag = write_bag(tmp_path / ("bad.bag" if ros1 else "bad"), TumSequence(sample_dir), ros1=ros1, colour="rgb8",
                    depth="32FC1", n=3, tf=False, info_fields=fields)
    with pytest.raises(DatasetError, match=re.escape(needle)):
        RosbagSequence(bag)
    assert main(["run", str(bag), "--out", str(tmp_path / "o"), "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bag}: /camera/rgb/camera_info: " in err and needle in err
    # a given camera replaces the camera info
    assert RosbagSequence(bag, camera="fr1").camera.name == "fr1"


@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["ros1", "ros2_mcap"])
def test_bag_reader_streams_in_order_with_camera_info(fr1_desk_dir, tmp_path, kind):
    seq = TumSequence(fr1_desk_dir)
    path = tmp_path / ("d.bag" if kind == "ros1" else "d_mcap")
    bag = write_bag(path, seq, ros1=kind == "ros1", colour="rgb8", depth="32FC1", n=6, mcap=kind == "ros2_mcap")
    rs = RosbagSequence(bag)
    assert len(rs) == 6 and rs.camera_frame == FRAME and rs.gt_valid.all()
    assert (rs.camera.fx, rs.camera.cy, rs.camera.dist) == (517.3, 255.3, tuple(FR1_D))
    np.testing.assert_allclose(rs.timestamps, seq.timestamps[:6], atol=1e-6)
    np.testing.assert_allclose(rs.groundtruth, seq.groundtruth[:6], atol=1e-6)
    load = rs.loader(6)
    for i in range(6):
        grey, depth = load(i)
        bgr = cv2.imread(seq.rgb_paths[i], cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(grey, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
        np.testing.assert_array_equal(depth, load_depth(seq.depth_paths[i], 5000.0))


@pytest.mark.slow
@pytest.mark.realdata
def test_bag_images_are_streamed_memory_stays_flat(fr1_rpy_dir, tmp_path):
    """Peak memory while decoding a bag's frames one by one does not grow with the bag's length."""
    import tracemalloc

    seq = TumSequence(fr1_rpy_dir)
    peaks = {}
    for n in (6, 24):
        rs = RosbagSequence(write_bag(tmp_path / f"b{n}.bag", seq, ros1=True, colour="rgb8", depth="32FC1", n=n,
                                      tf=False))
        tracemalloc.start()
        try:
            count = sum(1 for _ in rs.images())
            peaks[n] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert count == n
    frame_bytes = 640 * 480 * (3 + 4)  # one colour and one depth message
    assert peaks[24] < 1.3 * peaks[6]
    assert peaks[24] < 12 * frame_bytes  # holding all 24 frames would take 24


@pytest.mark.realdata
def test_evaluate_takes_bags_and_folders(fr1_desk_dir, tmp_path, capsys):
    import csv

    seq = TumSequence(fr1_desk_dir)
    bag = write_bag(tmp_path / "desk.bag", seq, ros1=True, colour="rgb8", depth="32FC1", n=6)
    assert main(["evaluate", str(bag), str(fr1_desk_dir), "--out", str(tmp_path / "study"), "--workers", "1",
                 "--max-frames", "6", "--no-plots", "--quiet"]) == 0
    with open(tmp_path / "study" / "summary.csv") as f:
        rows = {r["sequence"]: r for r in csv.DictReader(f)}
    assert set(rows) == {"desk", fr1_desk_dir.name}
    assert rows["desk"]["frames"] == rows[fr1_desk_dir.name]["frames"] == "6"
    assert (tmp_path / "study" / "desk" / "graph.g2o").is_file()
    # the bag's frames differ from the folder's only by the grey conversion: close, not equal
    a, b = float(rows["desk"]["rpe1_m"]), float(rows[fr1_desk_dir.name]["rpe1_m"])
    assert abs(a - b) < 0.5 * b


def test_bag_output_never_replaces_the_users_files(sample_dir, tmp_path, capsys):
    out = tmp_path / "o"
    args = ["run", str(sample_dir), "--out", str(out), "--max-frames", "3", "--quiet", "--no-plots"]
    assert main(args) == 0
    earlier = (out / "relative.txt").read_text()
    for fmt, name in (("ros1", "odometry.bag"), ("ros2", "odometry")):
        (out / name).write_text("the user's notes")
        assert main([*args, "--bag-out", fmt]) == 2
        assert "cannot be recognised as a bag covo wrote" in capsys.readouterr().err
        assert (out / name).read_text() == "the user's notes"
        assert (out / "relative.txt").read_text() == earlier  # refused before the earlier results went
        (out / name).unlink()
    # a ROS 1 bag a killed writer left (header, no index) and a symbolic link loop: one line, kept
    (out / "odometry.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(64))
    assert main([*args, "--bag-out", "ros1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot be recognised as a bag covo wrote" in err
    assert (out / "odometry.bag").stat().st_size == 77
    (out / "odometry.bag").unlink()
    (out / "odometry.bag").symlink_to("odometry.bag")
    assert main([*args, "--bag-out", "ros1"]) == 2
    assert capsys.readouterr().err.count("\n") == 1 and (out / "odometry.bag").is_symlink()
    (out / "odometry.bag").unlink()
    # covo's own bag is replaced by the next run's, and removed by a run that writes none or the other
    # format (the folder describes one run); a user's file of a bag's name stays
    assert main([*args, "--bag-out", "ros2"]) == 0 and (out / "odometry" / "metadata.yaml").is_file()
    assert main([*args, "--bag-out", "ros2"]) == 0 and (out / "odometry" / "metadata.yaml").is_file()
    assert main([*args, "--bag-out", "ros1"]) == 0 and (out / "odometry.bag").is_file()
    assert not (out / "odometry").exists()
    (out / "odometry").mkdir()
    (out / "odometry" / "notes.txt").write_text("the user's")
    assert main(args) == 0 and not (out / "odometry.bag").exists()
    assert (out / "odometry" / "notes.txt").read_text() == "the user's"
    shutil.rmtree(out / "odometry")
    # a user's ROS 2 recording of that name (other topics) is not covo's: refused as output, kept
    write_bag(out / "odometry", TumSequence(sample_dir), ros1=False, colour="rgb8", depth="32FC1", n=3)
    assert main([*args, "--bag-out", "ros2"]) == 2
    assert "is not a bag written by covo (topics /camera/" in capsys.readouterr().err
    assert main(args) == 0 and (out / "odometry" / "metadata.yaml").is_file()


def test_bag_output_never_replaces_the_bag_it_reads(sample_dir, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    bag = write_bag(out / "odometry.bag", TumSequence(sample_dir), ros1=True, colour="rgb8", depth="32FC1", n=3)
    assert main(["run", str(bag), "--out", str(out), "--quiet", "--no-plots", "--bag-out", "ros1"]) == 2
    assert "is the sequence this run reads" in capsys.readouterr().err
    assert bag.is_file() and RosbagSequence(bag).timestamps.shape == (3,)


def _shifted_copy(sample_dir: Path, dest: Path, shift_s: int) -> Path:
    """The sample with every stamp of rgb.txt, depth.txt and groundtruth.txt moved by ``shift_s``
    (whole seconds, in decimal: the stamps keep their digits), its images linked."""
    dest.mkdir()
    for sub in ("rgb", "depth"):
        (dest / sub).symlink_to(sample_dir / sub)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = []
        for line in (sample_dir / name).read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                stamp, rest = line.split(" ", 1)
                line = f"{Decimal(stamp) + shift_s} {rest}"
            lines.append(line)
        (dest / name).write_text("\n".join(lines) + "\n")
    return dest


def test_a_folders_bag_carries_the_stamps_of_rgb_txt_to_the_nanosecond(sample_dir, tmp_path):
    # rgb.txt's decimals, read as text (not through a float, which near 1.3e9 s holds the stamp only
    # to about 0.2 us), against the bag's header stamps and record times, read back with rosbags
    rows = [line.split()[0] for line in (sample_dir / "rgb.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")][:6]
    expected = [(int(a), int(b.ljust(9, "0"))) for a, b in (r.split(".") for r in rows)]
    for fmt, name in (("ros1", "odometry.bag"), ("ros2", "odometry")):
        out = tmp_path / fmt
        _run(["run", str(sample_dir), "--out", str(out), "--max-frames", "6", "--bag-out", fmt])
        with AnyReader([out / name]) as reader:
            conns = [c for c in reader.connections if c.topic == "/covo/odometry"]
            got = [(ns, reader.deserialize(raw, c.msgtype).header.stamp) for c, ns, raw in reader.messages(conns)]
        assert [(st.sec, st.nanosec) for _, st in got] == expected
        assert [ns for ns, _ in got] == [a * 10**9 + b for a, b in expected]


def test_stamps_a_bag_cannot_hold_are_refused_before_the_run(sample_dir, tmp_path, capsys):
    # ROS 1 stamps are unsigned, ROS 2's signed 32-bit seconds: refused with one line and exit 2
    # before anything is written, not a traceback halfway through the run
    early = _shifted_copy(sample_dir, tmp_path / "early_freiburg1", -1305031232)  # the first stamp at -2.47 s
    late = _shifted_copy(sample_dir, tmp_path / "late_freiburg1", 1_000_000_000)  # in 2043
    for seq, fmt, hint in ((early, "ros1", "--bag-out ros2"), (late, "ros2", "shift the stamps"),
                           (late, "ros1", "shift the stamps")):
        out = tmp_path / f"{seq.name}_{fmt}"
        assert main(["run", str(seq), "--out", str(out), "--max-frames", "4", "--quiet", "--no-plots",
                     "--bag-out", fmt]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "cannot be written to a ROS" in err and hint in err, err
        assert not out.exists() or not any(out.iterdir())
    # what a bag can hold runs: negative stamps in ROS 2
    _run(["run", str(early), "--out", str(tmp_path / "o2"), "--max-frames", "4", "--bag-out", "ros2"])
    with AnyReader([tmp_path / "o2" / "odometry"]) as reader:
        first = next(reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                     if c.topic == "/covo/odometry")
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (-3, 528748000)


def test_chain_samples_need_exactly_one_moving_link():
    from covo_gtsam.datasets.rosbag import _chain_samples
    from covo_gtsam.geometry import matrix_to_quat

    def link(stamps, poses, static=False):
        return {"static": static, "s": [(t, tuple(P[:3, 3]), tuple(matrix_to_quat(P[:3, :3])))
                                        for t, P in zip(stamps, poses)]}

    def pose(rx, ry, rz, t):
        return gtsam.Pose3(gtsam.Rot3.RzRyRx(rx, ry, rz), np.array(t, float)).matrix()

    A = pose(0.3, -0.2, 0.1, [0.5, 0.0, 1.0])  # world -> rig, fixed
    C = pose(-1.5708, 0.0, -1.5708, [0.0, -0.02, 0.0])  # camera -> optical, fixed (on /tf, constant)
    M = [pose(0.01 * k, 0.2, -0.1 * k, [k, 0.3, -k]) for k in (2, 1, 3, 1)]  # moving, out of order, a repeat
    stamps, poses = _chain_samples([link([0.0], [A], static=True), link([0.2, 0.1, 0.3, 0.1], M),
                                    link([0.0, 1.0], [C, C])])
    np.testing.assert_allclose(stamps, [0.1, 0.2, 0.3])  # in time order, the repeated stamp once (the first)
    np.testing.assert_allclose(poses, [A @ M[k] @ C for k in (1, 0, 2)], atol=1e-9)  # parent first
    assert _chain_samples([link([0.2, 0.1], M[:2]), link([0.0, 1.0], M[2:])]) is None  # two moving links
    assert _chain_samples([link([0.0], [A], static=True)]) is None  # none


def test_a_library_error_over_several_lines_is_one_line(tmp_path, capsys):
    """A ROS 2 bag folder whose metadata.yaml does not parse: the YAML parser's message runs over
    several lines (with a caret line); covo still ends with exit 2 and one line."""
    bag = tmp_path / "broken_bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(": : [\n")
    capsys.readouterr()
    assert main(["run", str(bag), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("covo: error: ") and "metadata.yaml" in err


def _imu_bag(path, ros1: bool, samples, topic: str = "/camera/imu", empty_topic: str | None = "/imu"):
    """A bag of ``sensor_msgs/Imu`` messages ``(t, wx, wy, wz)`` on ``topic`` in the order given, and on
    ``empty_topic`` accelerometer-only messages (angular_velocity_covariance[0] = -1, as the TUM bags' /imu)."""
    ts = _typestore(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(path, version=8), ts.serialize_cdr
    imu_t = "sensor_msgs/msg/Imu"
    T = ts.types
    writer.open()

    def imu(t, w, covariance):
        vec = T["geometry_msgs/msg/Vector3"]
        return T[imu_t](header=_header(ts, ros1, t, "camera_imu_optical_frame"),
                        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                        orientation_covariance=np.full(9, -1.0), angular_velocity=vec(x=w[0], y=w[1], z=w[2]),
                        angular_velocity_covariance=np.full(9, covariance),
                        linear_acceleration=vec(x=0.0, y=9.8, z=0.0), linear_acceleration_covariance=np.zeros(9))

    conn = writer.add_connection(topic, imu_t, typestore=ts)
    for i, (t, *w) in enumerate(samples):
        writer.write(conn, int(round(1e9 * (1000.0 + i))), ser(imu(t, w, 0.0), imu_t))
    if empty_topic:
        other = writer.add_connection(empty_topic, imu_t, typestore=ts)
        for i, (t, *_) in enumerate(samples):
            writer.write(other, int(round(1e9 * (1000.0 + i))), ser(imu(t, (0.0, 0.0, 0.0), -1.0), imu_t))
    writer.close()


@pytest.mark.parametrize("ros1", [True, False])
def test_a_gyroscope_from_a_bags_imu_topic(tmp_path, ros1):
    """``read_gyro``: angular velocities by header stamp, sorted (a bag holds them as they arrived), a
    repeated stamp once; an accelerometer-only topic, a missing topic and another message type are
    refused in one line that names the bag and the topic."""
    from covo_gtsam.datasets.rosbag import read_gyro

    samples = [(10.00, 0.1, 0.2, 0.3), (10.01, 0.2, 0.3, 0.4), (10.005, 0.15, 0.25, 0.35), (10.01, 9.0, 9.0, 9.0),
               (10.02, 0.3, 0.4, 0.5)]
    path = tmp_path / ("imu.bag" if ros1 else "imu")
    _imu_bag(path, ros1, samples)
    gyro = read_gyro(path, time_offset_s=0.5)
    np.testing.assert_allclose(gyro.stamps, [10.5, 10.505, 10.51, 10.52], atol=1e-9)
    np.testing.assert_allclose(gyro.angular_velocity(10.5075), [0.175, 0.275, 0.375], atol=1e-9)
    with pytest.raises(DatasetError, match=r"topic /imu gives no angular velocity: all 5 say"):
        read_gyro(path, "/imu")
    with pytest.raises(DatasetError, match=r"no topic /gyro in the bag \(topics: /camera/imu, /imu\)"):
        read_gyro(path, "/gyro")


def test_covo_run_takes_the_gyroscope_from_a_bag(tmp_path, sample_dir, capsys):
    """``covo run SEQ --gyro BAG --gyro-topic T``: the angular velocities of the reference's motion
    written as Imu messages compensate every pair; a colour topic is not an Imu topic."""
    from covo_gtsam.sequence_simulation import RecordedMotion

    motion = RecordedMotion.from_tum(sample_dir / "groundtruth.txt", 0.0, 0.02)
    first = float(load_tum_trajectory(sample_dir / "groundtruth.txt")[0][0])
    t = np.arange(motion.span[0] + 0.01, motion.span[1] - 0.01, 0.005)
    _imu_bag(tmp_path / "imu.bag", True, np.column_stack([t + first, motion.angular_velocity(t)]), topic="/gyro",
             empty_topic=None)
    base = ["run", str(sample_dir), "--max-frames", "6", "--no-plots", "--quiet"]
    gyro = ["--gyro", str(tmp_path / "imu.bag"), "--gyro-topic", "/gyro"]
    assert main([*base, "--out", str(tmp_path / "o"), *gyro]) == 0
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["gyro"]["pairs"] == m["nees_pairs"] == 5
    capsys.readouterr()
    seq = TumSequence(sample_dir)
    write_bag(tmp_path / "cam.bag", seq, True, "rgb8", "32FC1", n=2, tf=False)
    assert main([*base, "--out", str(tmp_path / "x"), "--gyro", str(tmp_path / "cam.bag"),
                 "--gyro-topic", "/camera/rgb/image_color"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has messages of type sensor_msgs/msg/Image, expected sensor_msgs/Imu" in err[0]
