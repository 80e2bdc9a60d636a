"""ROS bag output of an odometry run (``covo run --bag-out ros1|ros2``), with the pure-Python
``rosbags`` package (optional extra ``ros``).

``OUT/odometry.bag`` (ROS 1) or the folder ``OUT/odometry/`` (ROS 2, sqlite3) holds two topics,
one message per tracked frame, stamped with the frame's colour timestamp:

``/covo/odometry`` -- ``nav_msgs/Odometry``
    ``header.frame_id`` ``odom``: the first tracked camera frame (the ``world`` of
    ``trajectory.txt``), fixed and continuous as REP 105 asks of ``odom``. ``child_frame_id`` is the
    camera frame (the colour images' ``frame_id`` when the input is a bag, else ``camera``). Both
    are optical frames (z forward, x right, y down, REP 103's ``_optical`` suffix convention): put
    a static transform ahead of ``robot_localization`` to get a body frame.
    ``pose`` is ``T_odom,cam`` with ``step.pose_covariance`` (composed to first order along the
    trajectory) converted by :func:`covo_gtsam.covariance.tangent_to_ros`: covariance of the
    position error and of small rotations about the fixed axes of ``odom``, order
    ``[x y z rot_x rot_y rot_z]``. ``twist`` is the camera's mean body twist over the frame pair,
    ``Log(T_ref,cur) / dt`` (in ``child_frame_id``, as ROS requires), with covariance
    ``J Sigma J^T / dt^2`` reordered to ``[vx vy vz wx wy wz]`` (``J`` the derivative of Pose3's
    Logmap, ``Sigma`` the pair's covariance). The first frame of the run and the first of a new
    segment have no pair, so no twist: zero, with :data:`UNKNOWN_TWIST_VARIANCE` on the diagonal
    of its covariance (a zero covariance would tell a filter the camera is certainly at rest).

``/covo/relative`` -- ``geometry_msgs/PoseWithCovarianceStamped``
    One per estimated pair: the pose ``T_ref,cur`` (points of the current frame into the
    reference frame) with its covariance converted like the pose above, about the reference
    frame's axes. ``header.stamp`` is the current frame's time and ``header.frame_id`` names the
    reference frame as ``<camera frame>@<t_ref>`` (``t_ref`` in seconds, 6 decimals), since with
    keyframes the reference is not always the previous frame.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping, Sequence
from decimal import Decimal
from pathlib import Path

import gtsam
import numpy as np

from .covariance import tangent_to_ros
from .errors import ConfigError, DatasetError
from .geometry import matrix_to_quat

__all__ = ["BAG_FORMATS", "STAMP_SECONDS", "UNKNOWN_TWIST_VARIANCE", "OdometryBagWriter", "bag_output_path",
           "check_bag_stamps", "clear_bag_output", "require_rosbags"]

BAG_FORMATS = ("ros1", "ros2")
ODOMETRY_TOPIC = "/covo/odometry"
RELATIVE_TOPIC = "/covo/relative"
ODOM_FRAME = "odom"

_SWAP = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])


def require_rosbags():
    """Import ``rosbags``; :class:`ConfigError` with the install line when it is missing."""
    try:
        import rosbags  # noqa: F401  (only whether it is installed)
    except ImportError:
        raise ConfigError('ROS bags need the rosbags package: pip install "covo-gtsam[ros]" '
                          "(or pip install rosbags)") from None


def bag_output_path(out_dir: str | os.PathLike, fmt: str) -> Path:
    """``OUT/odometry.bag`` (ros1) or ``OUT/odometry`` (ros2)."""
    if fmt not in BAG_FORMATS:
        raise ConfigError(f"bag format must be one of {', '.join(BAG_FORMATS)}, got {fmt!r}")
    return Path(out_dir) / ("odometry.bag" if fmt == "ros1" else "odometry")


def _bag_topics(path: Path) -> tuple[set[str] | None, str]:
    """The topics of the bag at ``path`` (a ROS 1 bag file or a ROS 2 bag folder, not a symlink),
    or ``(None, why not)``."""
    try:
        if path.is_symlink():
            return None, "a symbolic link"
        if path.is_dir() and not (path / "metadata.yaml").is_file():
            return None, "a folder without a bag's metadata.yaml"
        if path.is_file():
            with open(path, "rb") as f:
                if f.read(13) != b"#ROSBAG V2.0\n":
                    return None, "not a ROS 1 bag"
        elif not path.is_dir():
            return None, "neither a file nor a folder"
        from rosbags.highlevel import AnyReader

        with AnyReader([path]) as reader:
            return {c.topic for c in reader.connections}, ""
    except Exception as exc:  # unreadable, unindexed (a killed writer), not a bag after all
        return None, " ".join(str(exc).split()) or type(exc).__name__


def clear_bag_output(out_dir: str | os.PathLike, fmt: str, inputs: tuple = (), remove: bool = True) -> None:
    """Make the bag output's path of ``fmt`` in ``out_dir`` free: an earlier bag covo wrote there
    (its topics are covo's own, :data:`ODOMETRY_TOPIC` and :data:`RELATIVE_TOPIC`; anything else is
    the user's) is removed (with ``remove``; without, only checked), nothing else is ever removed.

    Raises:
        DatasetError: something else is there (a user's file, folder or bag, or a bag that cannot be
            read, as one a killed run left), it is or holds one of ``inputs`` (the paths the run
            reads), or it cannot be removed.
    """
    path = bag_output_path(out_dir, fmt)
    if not (path.exists() or path.is_symlink()):
        return
    require_rosbags()  # to tell covo's bag from another one
    try:
        target = path.resolve()
        sources = [Path(src).resolve() for src in inputs if src is not None]
    except (OSError, RuntimeError) as exc:  # e.g. a symbolic link loop
        raise DatasetError(f"{path}: cannot be resolved ({exc}); remove it first") from None
    if any(src == target or target in src.parents for src in sources):
        raise DatasetError(f"{path}: is the sequence this run reads; choose another --out for the bag")
    topics, why = _bag_topics(path)
    if topics is None:
        raise DatasetError(f"{path}: exists and cannot be recognised as a bag covo wrote ({why}); remove it first")
    if not topics or not topics <= {ODOMETRY_TOPIC, RELATIVE_TOPIC}:  # covo's bags have both
        raise DatasetError(f"{path}: exists and is not a bag written by covo (topics {', '.join(sorted(topics))}); "
                           "remove it first")
    if remove:
        _remove_bag(path)


def _remove_bag(path: Path) -> None:
    """Remove covo's earlier bag at ``path`` (a file or a folder); :class:`DatasetError` if that fails."""
    try:
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot remove the earlier run's bag ({exc.strerror or exc})") from None


def remove_earlier_bags(out_dir: str | os.PathLike, keep: str | None, inputs: tuple = ()) -> None:
    """Remove the bags an earlier run of covo wrote in ``out_dir`` in the formats this run does not
    write (``keep``: the one it writes, or None), so the folder describes one run. A path there that
    is not recognisably covo's bag (a user's file, or rosbags not installed to tell) stays."""
    for fmt in BAG_FORMATS:
        if fmt == keep or not bag_output_path(out_dir, fmt).exists():
            continue
        try:
            clear_bag_output(out_dir, fmt, inputs, remove=False)  # only tells whether it is covo's
        except (ConfigError, DatasetError):
            continue  # not covo's, or cannot be told: left as it is
        _remove_bag(bag_output_path(out_dir, fmt))  # covo's: a removal that fails is an error


#: variance ((m/s)^2, (rad/s)^2) of each twist component where there is no pair to measure it
UNKNOWN_TWIST_VARIANCE = 1e6


#: the whole seconds a header stamp holds: ROS 2's ``builtin_interfaces/Time`` a signed 32-bit count;
#: ROS 1's ``time`` an unsigned one, which rosbags serialises through the signed type, so neither
#: negative nor beyond 2^31 - 1 (2038-01-19)
STAMP_SECONDS = {"ros1": (0, 2**31 - 1), "ros2": (-(2**31), 2**31 - 1)}


def check_bag_stamps(stamps: Sequence[float], fmt: str, what: str = "the stamps") -> None:
    """:class:`DatasetError` when a stamp (s) of ``stamps`` falls outside what a ``fmt`` bag's
    header stamps hold (:data:`STAMP_SECONDS`), before anything is written."""
    stamps = np.asarray(stamps, dtype=float)
    if stamps.size == 0:
        return
    lo, hi = STAMP_SECONDS[fmt]
    bad = (stamps < lo) | (stamps >= hi + 1)
    if np.any(bad):
        name = "ROS 1" if fmt == "ros1" else "ROS 2"
        raise DatasetError(f"{what}: {float(stamps[bad][0]):.6f} s cannot be written to a {name} bag, whose header "
                           f"stamps hold {lo} to {hi} s; shift the stamps"
                           + (" or write --bag-out ros2" if fmt == "ros1" and np.all(stamps >= -(2**31)) and
                              np.all(stamps < 2**31) else ""))


def _nanoseconds(t: float, exact: Mapping[float, int] | None = None) -> int:
    """Stamp ``t`` (s) in integer nanoseconds: ``exact``'s value for it where given (a bag's own
    stamps, which a float in seconds holds only to about 0.1 us today), else the shortest decimal
    that reads back as ``t``: a TUM stamp as its file wrote it (exact to the nanosecond for up to
    about 7 decimals, what such a float holds; TUM's have 6), rounded."""
    if exact is not None and float(t) in exact:
        return int(exact[float(t)])
    return int((Decimal(repr(float(t))) * 1_000_000_000).to_integral_value())


class OdometryBagWriter:
    """Writes ``/covo/odometry`` and ``/covo/relative`` (see the module docstring) message by message.

    ``write(step)`` takes each :class:`~covo_gtsam.steps.OdometryStep` in order (lost steps are
    skipped); use as a context manager, or call :meth:`close`.
    """

    def __init__(self, out_dir: str | os.PathLike, fmt: str, camera_frame: str = "camera",
                 stamps_ns: Mapping[float, int] | None = None) -> None:
        require_rosbags()
        from rosbags.typesys import Stores, get_typestore

        self.fmt = fmt
        self.path = bag_output_path(out_dir, fmt)
        self.camera_frame = camera_frame or "camera"
        self._stamps_ns = stamps_ns
        clear_bag_output(out_dir, fmt)
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self.ts = get_typestore(Stores.ROS1_NOETIC)
            self._writer = Writer(self.path)
            self._serialize = self.ts.serialize_ros1
        else:
            from rosbags.rosbag2 import Writer

            self.ts = get_typestore(Stores.ROS2_HUMBLE)
            self._writer = Writer(self.path, version=8)
            self._serialize = self.ts.serialize_cdr
        try:
            self._writer.open()
        except Exception as exc:  # rosbags raises its own writer errors
            raise DatasetError(f"{self.path}: cannot write the bag ({exc})") from exc
        self._odom = self._writer.add_connection(ODOMETRY_TOPIC, "nav_msgs/msg/Odometry", typestore=self.ts)
        self._rel = self._writer.add_connection(RELATIVE_TOPIC, "geometry_msgs/msg/PoseWithCovarianceStamped",
                                                typestore=self.ts)
        self._seq = 0
        self._closed = False

    # -- message building ---------------------------------------------------------------------
    def _header(self, ns: int, frame_id: str):
        T = self.ts.types
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if self.fmt == "ros1":
            return T["std_msgs/msg/Header"](seq=self._seq, stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _pose_with_covariance(self, pose: gtsam.Pose3, cov: np.ndarray):
        T = self.ts.types
        M = pose.matrix()
        q = matrix_to_quat(M[:3, :3])
        ros = tangent_to_ros(np.asarray(cov, dtype=float), pose)
        ros = 0.5 * (ros + ros.T)
        return T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(M[0, 3]), y=float(M[1, 3]), z=float(M[2, 3])),
                orientation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                              w=float(q[3]))),
            covariance=np.ascontiguousarray(ros.reshape(36), dtype=np.float64))

    def _twist(self, step):
        T = self.ts.types
        vec = T["geometry_msgs/msg/Vector3"]
        w = np.zeros(3)
        v = np.zeros(3)
        cov = UNKNOWN_TWIST_VARIANCE * np.eye(6)
        if step.has_relative_pose and step.relative is not None:
            dt = float(step.timestamp - step.ref_timestamp)
            if dt > 0:
                xi = gtsam.Pose3.Logmap(step.relative)
                w, v = xi[:3] / dt, xi[3:] / dt
                J = np.linalg.inv(gtsam.Pose3.ExpmapDerivative(xi))  # Jacobian of Logmap (right perturbation)
                cov = _SWAP @ (J @ step.covariance @ J.T) @ _SWAP / dt**2
                cov = 0.5 * (cov + cov.T)
        return T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=vec(x=float(v[0]), y=float(v[1]), z=float(v[2])),
                                               angular=vec(x=float(w[0]), y=float(w[1]), z=float(w[2]))),
            covariance=np.ascontiguousarray(cov.reshape(36), dtype=np.float64))

    def write(self, step) -> None:
        """Write the messages of one odometry step (nothing for a lost frame)."""
        if not step.has_pose:
            return
        T = self.ts.types
        check_bag_stamps([step.timestamp], self.fmt, f"frame stamp {step.timestamp!r}")
        ns = _nanoseconds(step.timestamp, self._stamps_ns)
        odom = T["nav_msgs/msg/Odometry"](
            header=self._header(ns, ODOM_FRAME), child_frame_id=self.camera_frame,
            pose=self._pose_with_covariance(step.pose, step.pose_covariance), twist=self._twist(step))
        self._writer.write(self._odom, ns, self._serialize(odom, "nav_msgs/msg/Odometry"))
        if step.has_relative_pose:
            rel = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=self._header(ns, f"{self.camera_frame}@{step.ref_timestamp:.6f}"),
                pose=self._pose_with_covariance(step.relative, step.covariance))
            self._writer.write(self._rel, ns, self._serialize(rel, "geometry_msgs/msg/PoseWithCovarianceStamped"))
        self._seq += 1

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
