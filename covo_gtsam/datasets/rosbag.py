"""ROS bag reader: a ROS 1 ``.bag`` file or a ROS 2 bag folder (sqlite3 or mcap), with the pure-Python
``rosbags`` package (optional extra ``ros``).

The bag is read twice and never held in memory: the constructor goes through the message
headers (stamps, encodings, the camera info, ``/tf``) and :meth:`RosbagSequence.images` decodes
the associated images in order while the odometry runs, holding only the few frames between a
colour image and its depth image.

* Topics: ``rgb_topic`` (default ``/camera/rgb/image_color``), ``depth_topic``
  (``/camera/depth/image``) and ``camera_info_topic`` (``/camera/rgb/camera_info``), the TUM RGB-D
  bags' names. Both image topics are ``sensor_msgs/Image``; colour encodings ``rgb8``, ``bgr8``,
  ``mono8`` (converted to grey with OpenCV's ``cvtColor``, ITU-R BT.601 weights), depth encodings
  ``32FC1`` (metres; NaN, inf and values <= 0 mean no measurement) and ``16UC1`` (millimetres,
  ``value * float32(1 / 1000)``, 0 = no measurement). Anything else is a :class:`DatasetError`
  naming the topic and the encoding.
* Frames: colour and depth are associated by ``header.stamp`` with the TUM rule
  (:func:`covo_gtsam.datasets.tum.associate`: at most 0.02 s apart, one-to-one, smallest difference
  first); a frame's timestamp is its colour stamp.
* Camera: intrinsics ``K`` and ``plumb_bob`` distortion ``D = [k1 k2 p1 p2 k3]`` of the first
  message on the camera-info topic, unless a camera is given (the message is then not read). It
  goes through the checks of a camera file (:mod:`covo_gtsam.camera_file`): one that fails them is a
  :class:`DatasetError` naming the bag and the topic.
* Ground truth: the chain of ``/tf`` and ``/tf_static`` transforms (``tf2_msgs/TFMessage``)
  from ``gt_parent`` (default ``world``) down to ``gt_frame`` (default: the colour images'
  ``frame_id``), e.g. in the TUM bags ``/world -> /kinect`` (motion capture) and the fixed links
  ``/kinect -> ... -> /openni_rgb_optical_frame``. Each link is interpolated at the frame stamps
  like ``groundtruth.txt`` (linear / slerp, no gap above 0.1 s, inside its span); a link from
  ``/tf_static`` or with a single distinct value is constant. ``T_world,cam`` is the product of
  the links; a frame has ground truth where every link has. Without a chain ``groundtruth`` is
  None and the run's accuracy metrics are skipped.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DatasetError, InputError
from ..geometry import make_pose, quat_to_matrix
from .tum import associate, interpolate_poses

__all__ = ["DEFAULT_GYRO_TOPIC", "DEFAULT_TOPICS", "RosbagSequence", "is_bag", "read_gyro"]

DEFAULT_TOPICS = {
    "rgb_topic": "/camera/rgb/image_color",
    "depth_topic": "/camera/depth/image",
    "camera_info_topic": "/camera/rgb/camera_info",
}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "mono8")
DEPTH_ENCODINGS = ("32FC1", "16UC1")
TF_TOPICS = ("/tf", "/tf_static")
#: ``sensor_msgs/Imu`` topic a gyroscope is read from (a RealSense driver's with unite_imu_method set)
DEFAULT_GYRO_TOPIC = "/camera/imu"
_MM = np.float32(1.0 / 1000.0)


def is_bag(path: str | os.PathLike) -> bool:
    """True for a ROS 1 ``.bag`` file or a ROS 2 bag folder (with ``metadata.yaml``)."""
    p = Path(path)
    return (p.is_file() and p.suffix.lower() == ".bag") or (p.is_dir() and (p / "metadata.yaml").is_file())


def _stamp(header) -> float:
    s = header.stamp
    return float(s.sec) + 1e-9 * float(s.nanosec)


def _stamp_ns(header) -> int:
    """The header's stamp in whole nanoseconds, exactly (a float in seconds is not, today)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _open_bag(path: Path):
    """An opened rosbags ``AnyReader`` of the bag at ``path`` (close it when done); a bag it cannot
    read is a :class:`DatasetError`."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags' reader errors have no common public base
        raise DatasetError(f"{path}: cannot read the bag ({exc})") from exc
    return reader


def read_gyro(path: str | os.PathLike, topic: str = DEFAULT_GYRO_TOPIC, rotation=None, time_offset_s: float = 0.0):
    """A :class:`~covo_gtsam.gyro.Gyroscope` from a bag's ``sensor_msgs/Imu`` topic: each message's
    ``header.stamp`` and ``angular_velocity`` (rad/s, in its ``frame_id``'s axes; ``rotation`` is
    ``R_cam_gyro``), in stamp order (a bag holds them in arrival order; a repeated stamp keeps its
    first message). Messages whose ``angular_velocity_covariance[0]`` is -1 hold no angular velocity
    (ROS's convention, e.g. the TUM bags' accelerometer on ``/imu``) and are left out; a topic with
    none left, of another type or missing is a :class:`DatasetError`."""
    from ..gyro import Gyroscope
    from ..ros_io import require_rosbags

    require_rosbags()
    p = Path(os.path.abspath(os.fspath(path)))
    if not p.exists():
        raise DatasetError(f"{p}: bag does not exist")
    reader = _open_bag(p)
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            topics = sorted({c.topic for c in reader.connections})
            raise DatasetError(f"{p}: no topic {topic} in the bag (topics: {', '.join(topics) or 'none'}); "
                               "choose the gyroscope's with --gyro-topic")
        if any(c.msgtype != "sensor_msgs/msg/Imu" for c in conns):
            raise DatasetError(f"{p}: topic {topic} has messages of type {conns[0].msgtype}, expected sensor_msgs/Imu")
        stamps, rates, empty = [], [], 0
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if msg.angular_velocity_covariance[0] == -1:
                empty += 1
                continue
            w = msg.angular_velocity
            stamps.append(_stamp(msg.header))
            rates.append((w.x, w.y, w.z))
    finally:
        reader.close()
    if not stamps:
        why = f"all {empty} say they hold no angular velocity (covariance -1)" if empty else "it has no message"
        raise DatasetError(f"{p}: topic {topic} gives no angular velocity: {why}")
    t = np.array(stamps)
    order = np.argsort(t, kind="stable")
    t, w = t[order], np.array(rates, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    try:
        return Gyroscope(t[keep], w[keep], rotation=rotation, time_offset_s=time_offset_s)
    except InputError as exc:
        raise DatasetError(f"{p}: topic {topic}: {exc}") from None


def _field(msg, *names):
    """The first of ``names`` that ``msg`` has (ROS 1 ``K`` vs ROS 2 ``k``)."""
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def decode_colour(msg, topic: str = "") -> np.ndarray:
    """Grey uint8 (H, W) of a ``sensor_msgs/Image`` in rgb8, bgr8 or mono8."""
    from .images import to_grey

    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), msg.encoding
    channels = {"rgb8": 3, "bgr8": 3, "mono8": 1}.get(enc)
    if channels is None:
        raise DatasetError(f"{topic}: image encoding {enc!r} is not supported for colour "
                           f"({', '.join(COLOUR_ENCODINGS)})")
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * channels or data.size < h * step:
        raise InputError(f"{topic}: image of {w}x{h} {enc} has {data.size} bytes, step {step}")
    img = data[: h * step].reshape(h, step)[:, : w * channels]
    if channels == 1:
        return np.ascontiguousarray(img)
    return to_grey(img.reshape(h, w, 3), bgr=(enc == "bgr8"))


def decode_depth(msg, topic: str = "") -> np.ndarray:
    """Depth in metres, float32 (H, W), 0 = no measurement, of a ``sensor_msgs/Image`` in 32FC1 or 16UC1."""
    h, w, step, enc = int(msg.height), int(msg.width), int(msg.step), msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise DatasetError(f"{topic}: image encoding {enc!r} is not supported for depth "
                           f"({', '.join(DEPTH_ENCODINGS)})")
    size = 4 if enc == "32FC1" else 2
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * size or data.size < h * step:
        raise InputError(f"{topic}: image of {w}x{h} {enc} has {data.size} bytes, step {step}")
    rows = data[: h * step].reshape(h, step)[:, : w * size]
    order = ">" if msg.is_bigendian else "<"
    if enc == "32FC1":
        d = rows.copy().view(order + "f4").reshape(h, w).astype(np.float32)
        d[~(np.isfinite(d) & (d > 0))] = 0.0
        return d
    raw = rows.copy().view(order + "u2").reshape(h, w)
    return raw.astype(np.float32) * _MM


def _link_poses(link: dict) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (M,) and poses (M, 4, 4) of a tf link's samples."""
    stamps = np.array([x[0] for x in link["s"]])
    return stamps, make_pose(quat_to_matrix(np.array([x[2] for x in link["s"]])), np.array([x[1] for x in link["s"]]))


def _is_fixed(link: dict, poses: np.ndarray) -> bool:
    return link["static"] or np.ptp(poses, axis=0).max() == 0


def _chain_samples(links: list[dict]) -> tuple[np.ndarray, np.ndarray] | None:
    """The chain's poses (parent first) at the samples of its one moving link (one per stamp, the
    first, in time order), the fixed links composed in (their last pose), or None without exactly
    one moving link."""
    parts = [_link_poses(link) for link in links]
    moving = [i for i, (link, (_, poses)) in enumerate(zip(links, parts)) if not _is_fixed(link, poses)]
    if len(moving) != 1:
        return None
    stamps, samples = parts[moving[0]]
    before, after = np.eye(4), np.eye(4)
    for i, (_, poses) in enumerate(parts):
        if i < moving[0]:
            before = before @ poses[-1]
        elif i > moving[0]:
            after = after @ poses[-1]
    order = np.argsort(stamps, kind="stable")
    stamps, samples = stamps[order], samples[order]
    _, first = np.unique(stamps, return_index=True)  # a stamp published twice counts once
    return stamps[first], before @ samples[first] @ after


class RosbagSequence:
    """A ROS bag with colour and depth image topics, read like a
    :class:`~covo_gtsam.datasets.tum.TumSequence`.

    Attributes: ``path``, ``name`` (file or folder name without ``.bag``), ``timestamps`` (colour
    stamps of the associated frames, s, (K,)), ``groundtruth`` (T_world,cam (K, 4, 4) from ``/tf``, or
    None), ``gt_valid`` (K,), ``gt_samples`` (the ground truth's own samples ``(stamps (M,) s,
    T_world,cam (M, 4, 4))`` at the stamps of the chain's one moving link, the fixed links composed
    in; None without a chain or without exactly one moving link), ``camera`` (the given camera or
    preset name, else the one of the camera info), ``camera_frame`` (the colour images'
    ``frame_id``), ``missing_files`` (empty).
    Images are decoded by :meth:`images`.

    Raises:
        ConfigError: ``rosbags`` is not installed.
        DatasetError: the bag cannot be read, a topic is missing or has another message type, an
            encoding is not supported, the camera info fails the camera checks (without a given
            camera), or no frame can be associated.
    """

    def __init__(self, path: str | os.PathLike, camera=None, rgb_topic: str = DEFAULT_TOPICS["rgb_topic"],
                 depth_topic: str = DEFAULT_TOPICS["depth_topic"],
                 camera_info_topic: str = DEFAULT_TOPICS["camera_info_topic"], gt_frame: str | None = None,
                 gt_parent: str = "world",
                 max_dt: float = 0.02, max_gap: float = 0.1) -> None:
        from ..ros_io import require_rosbags

        require_rosbags()
        self.path = Path(os.path.abspath(os.fspath(path)))
        if not self.path.exists():
            raise DatasetError(f"{self.path}: bag does not exist")
        self.name = self.path.stem if self.path.is_file() else self.path.name
        self.rgb_topic, self.depth_topic, self.camera_info_topic = rgb_topic, depth_topic, camera_info_topic
        self.missing_files: list[str] = []
        if isinstance(camera, str):
            from ..camera import Camera

            camera = Camera.preset(camera)
        self._camera = camera
        self._info_camera = None
        self.gt_parent = gt_parent.lstrip("/")
        self._scan(gt_frame, max_dt, max_gap)

    # -- reading ------------------------------------------------------------------------------
    def _connections(self, reader, topic: str, required: bool = True):
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns and required:
            topics = sorted({c.topic for c in reader.connections})
            raise DatasetError(f"{self.path}: no topic {topic} in the bag (topics: {', '.join(topics) or 'none'}); "
                               "choose one with --rgb-topic / --depth-topic / --camera-info-topic")
        for c in conns:
            if topic in (self.rgb_topic, self.depth_topic) and c.msgtype != "sensor_msgs/msg/Image":
                raise DatasetError(f"{self.path}: topic {topic} has messages of type {c.msgtype}, "
                                   "expected sensor_msgs/Image")
        return conns

    def _scan(self, gt_frame, max_dt: float, max_gap: float) -> None:
        reader = _open_bag(self.path)
        try:
            rgb_c = self._connections(reader, self.rgb_topic)
            depth_c = self._connections(reader, self.depth_topic)
            info_c = self._connections(reader, self.camera_info_topic, required=False)
            tf_c = [c for c in reader.connections if c.topic in TF_TOPICS]
            rgb_t, rgb_ns, depth_t = [], [], []
            frame_id = ""
            tf: dict[str, dict] = {}  # child frame -> parent, static, samples (stamp, position, quaternion)
            for conn, _, raw in reader.messages(connections=rgb_c + depth_c + info_c + tf_c):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == self.rgb_topic:
                    if msg.encoding not in COLOUR_ENCODINGS:
                        raise DatasetError(f"{self.path}: topic {conn.topic} has image encoding {msg.encoding!r}; "
                                           f"colour must be one of {', '.join(COLOUR_ENCODINGS)}")
                    rgb_t.append(_stamp(msg.header))
                    rgb_ns.append(_stamp_ns(msg.header))
                    frame_id = frame_id or msg.header.frame_id
                elif conn.topic == self.depth_topic:
                    if msg.encoding not in DEPTH_ENCODINGS:
                        raise DatasetError(f"{self.path}: topic {conn.topic} has image encoding {msg.encoding!r}; "
                                           f"depth must be one of {', '.join(DEPTH_ENCODINGS)}")
                    depth_t.append(_stamp(msg.header))
                elif conn.topic == self.camera_info_topic:
                    if self._info_camera is None and self._camera is None:  # a given camera replaces it
                        self._info_camera = self._camera_from_info(msg)
                else:
                    static = conn.topic == "/tf_static"
                    for tr in msg.transforms:
                        q = tr.transform.rotation
                        p = tr.transform.translation
                        link = tf.setdefault(tr.child_frame_id.lstrip("/"),
                                             {"parent": tr.header.frame_id.lstrip("/"), "static": static, "s": []})
                        link["s"].append((_stamp(tr.header), (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)))
        finally:
            reader.close()

        self._rgb_t, self._depth_t = np.array(rgb_t), np.array(depth_t)
        pairs = associate(self._rgb_t, self._depth_t, max_dt)
        if not pairs:
            raise DatasetError(
                f"{self.path}: no frame could be associated: no colour stamp of {self.rgb_topic} ({len(rgb_t)} "
                f"messages) has a depth stamp of {self.depth_topic} ({len(depth_t)} messages) within {max_dt} s")
        self._rgb_index = np.array([i for i, _ in pairs], dtype=int)
        self._depth_index = np.array([j for _, j in pairs], dtype=int)
        self.timestamps = self._rgb_t[self._rgb_index]
        #: the colour messages' stamps exactly, in integer nanoseconds (the output bag's stamps)
        self.timestamps_ns = np.array(rgb_ns, dtype=np.int64)[self._rgb_index]
        #: the associated depth images' stamps (s): the run takes each frame's colour-depth offset from them
        self.depth_timestamps = self._depth_t[self._depth_index]
        self.camera_frame = frame_id.lstrip("/") or "camera"
        self.gt_frame = (gt_frame or self.camera_frame).lstrip("/")
        self.groundtruth = None
        self.gt_samples = None
        self.gt_valid = np.zeros(len(self.timestamps), bool)
        chain = []
        frame = self.gt_frame
        while frame != self.gt_parent and frame in tf and len(chain) < 64:
            chain.append(tf[frame])
            frame = tf[frame]["parent"]
        if chain and frame == self.gt_parent:
            self.groundtruth, self.gt_valid = self._compose_chain(chain[::-1], max_gap)
            self.gt_samples = _chain_samples(chain[::-1])

    def _compose_chain(self, links: list[dict], max_gap: float) -> tuple[np.ndarray, np.ndarray]:
        """``T_world,cam`` (K, 4, 4) and validity (K,) at the frame stamps from tf links, parent first."""
        K = len(self.timestamps)
        total = np.tile(np.eye(4), (K, 1, 1))
        valid = np.ones(K, bool)
        for link in links:
            stamps, poses = _link_poses(link)
            if _is_fixed(link, poses):
                T, ok = np.broadcast_to(poses[-1], (K, 4, 4)), np.ones(K, bool)
            else:
                T, ok = interpolate_poses(stamps, poses, self.timestamps, max_gap)
            total = total @ T
            valid &= ok
        total[~valid] = np.eye(4)
        return total, valid

    def _camera_from_info(self, msg):
        """The camera of a ``sensor_msgs/CameraInfo`` message, through the checks of a camera file
        (:func:`~covo_gtsam.camera_file.checked_camera`: ``K`` without skew and with the third row
        ``0 0 1``, the principal point inside the image, focal lengths in range, a ``plumb_bob``
        distortion invertible over the image)."""
        from ..camera_file import check_camera_matrix, checked_camera, plumb_bob

        where = f"{self.path}: {self.camera_info_topic}"
        try:
            K = [float(k) for k in _field(msg, "k", "K")]
            check_camera_matrix(where, K, key="K", item="K")
            dist = plumb_bob(where, msg.distortion_model, _field(msg, "d", "D"))
            values = {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5], "dist": dist, "width": int(msg.width),
                      "height": int(msg.height), "name": "camera_info"}
            return checked_camera(where, values)
        except ConfigError as exc:
            raise DatasetError(f"{exc}; pass --camera") from exc

    @property
    def camera(self):
        """The camera given to the constructor, else the one of the first camera-info message."""
        if self._camera is None:
            if self._info_camera is None:
                raise DatasetError(f"{self.path}: no message on {self.camera_info_topic}; pass a camera "
                                   "(CLI: --camera) or --camera-info-topic")
            self._camera = self._info_camera
        return self._camera

    def images(self, n: int | None = None):
        """``(grey uint8 (H, W), depth float32 metres (H, W))`` of frames ``0 .. n-1`` in order,
        decoded from the bag as it is read; a frame that cannot be decoded yields an
        :class:`InputError` in its place (the run reports it lost)."""
        n = len(self) if n is None else min(int(n), len(self))
        if n <= 0:
            return
        rgb_need = {int(i): k for k, i in enumerate(self._rgb_index[:n])}
        depth_need = {int(j): k for k, j in enumerate(self._depth_index[:n])}
        colour: dict[int, object] = {}
        depth: dict[int, object] = {}
        counts = {self.rgb_topic: -1, self.depth_topic: -1}
        nxt = 0
        reader = _open_bag(self.path)
        try:
            conns = self._connections(reader, self.rgb_topic) + self._connections(reader, self.depth_topic)
            for conn, _, raw in reader.messages(connections=conns):
                counts[conn.topic] += 1
                is_rgb = conn.topic == self.rgb_topic
                k = (rgb_need if is_rgb else depth_need).get(counts[conn.topic])
                if k is None:
                    continue
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    item = decode_colour(msg, conn.topic) if is_rgb else decode_depth(msg, conn.topic)
                except (InputError, DatasetError) as exc:
                    item = InputError(str(exc))
                (colour if is_rgb else depth)[k] = item
                while nxt < n and nxt in colour and nxt in depth:
                    c, d = colour.pop(nxt), depth.pop(nxt)
                    err = c if isinstance(c, InputError) else d if isinstance(d, InputError) else None
                    yield err if err is not None else (c, d)
                    nxt += 1
                if nxt >= n:
                    return
        finally:
            reader.close()

    def loader(self, n: int | None = None):
        """A thread-safe function ``i -> images(n)[i]`` for ``i = 0, 1, ...`` called roughly in order
        (decoded frames wait in a small buffer until asked for)."""
        it = iter(self.images(n))
        lock = threading.Lock()
        buf: dict[int, object] = {}
        produced = [0]

        def load(i: int):
            with lock:
                while i not in buf:
                    try:
                        buf[produced[0]] = next(it)
                    except StopIteration:
                        raise InputError(f"{self.path}: frame {i} is not in the bag") from None
                    produced[0] += 1
                return buf.pop(i)

        return load

    def __len__(self) -> int:
        return len(self.timestamps)

    def frames(self, start: int, stop: int | None = None) -> "RosbagSequence":
        """The same bag restricted to frames ``start`` to ``stop - 1`` (a copy)."""
        import copy

        stop = len(self) if stop is None else stop
        if not (isinstance(start, int) and isinstance(stop, int) and 0 <= start < stop <= len(self)):
            raise ConfigError(f"frames need 0 <= start < stop <= {len(self)}, got {start!r}, {stop!r}")
        part = copy.copy(self)
        part._rgb_index, part._depth_index = self._rgb_index[start:stop], self._depth_index[start:stop]
        part.timestamps = self.timestamps[start:stop]
        part.depth_timestamps = self.depth_timestamps[start:stop]
        part.gt_valid = self.gt_valid[start:stop]
        part.groundtruth = None if self.groundtruth is None else self.groundtruth[start:stop]
        return part

    def __repr__(self) -> str:
        gt = "no ground truth" if self.groundtruth is None else f"{int(self.gt_valid.sum())} with ground truth"
        return f"RosbagSequence({self.name!r}, {len(self)} frames, {gt})"
