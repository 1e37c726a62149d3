"""Which topics of a ROS 2 bag feed which channels: the topic map, read from YAML (drivers/rosbag_topics.yaml holds
the defaults and says what each key means)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from drivers.source import check_positive
from texture_library.channels import UNIT_SCALE

DEFAULT_TOPICS_FILE = Path(__file__).with_name("rosbag_topics.yaml")

#: the message types each channel reads, and the field it takes
IMU = "sensor_msgs/msg/Imu"
WRENCH = "geometry_msgs/msg/WrenchStamped"
TWIST = "geometry_msgs/msg/TwistStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
CHANNEL_TYPES: dict[str, tuple[str, ...]] = {
    "accel": (IMU,),
    "force": (WRENCH,),
    "speed": (TWIST, ODOMETRY, POSE),
    "frames": (COMPRESSED_IMAGE, IMAGE),
}
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class TopicMap:
    """Topics (None: the bag's one topic of a type the channel reads), units and geometry.

    force_frame: the header.frame_id the wrench must carry (None: any one); normal_axis: index 0–2 of the axis the
    tool presses along, normal_sign ±1; speed_axes: indices of the axes whose velocity norm is the scanning speed.
    max_gap_s: a longer hole in a topic's stamps ends its run; reorder_s: how far back a stamp may step and be put
    back in order.
    """

    accel_topic: str | None = None
    accel_units: str = "m/s^2"
    force_topic: str | None = None
    force_frame: str | None = None
    normal_axis: int = 2
    normal_sign: float = 1.0
    force_units: str = "N"
    speed_topic: str | None = None
    speed_axes: tuple[int, ...] = (0, 1)
    speed_units: str = "m/s"
    frames_topic: str | None = None
    max_gap_s: float = 0.05
    reorder_s: float = 0.01

    def topic(self, channel: str) -> str | None:
        return {
            "accel": self.accel_topic,
            "force": self.force_topic,
            "speed": self.speed_topic,
            "frames": self.frames_topic,
        }[channel]


def _section(doc: dict, name: str, keys: tuple[str, ...], where: str) -> dict:
    sec = doc.get(name) or {}
    if not isinstance(sec, dict):
        raise ValueError(f"{where}: {name} must be a mapping of {list(keys)}, got {sec!r}")
    unknown = sorted(set(sec) - set(keys))
    if unknown:
        raise ValueError(f"{where}: {name}: unknown key(s) {unknown}; expected some of {list(keys)}")
    topic = sec.get("topic")
    if topic is not None and not (isinstance(topic, str) and topic.startswith("/")):
        raise ValueError(f"{where}: {name}.topic must be a topic name starting with '/' or null, got {topic!r}")
    return sec


def _units(sec: dict, kind: str, default: str, where: str) -> str:
    units = sec.get("units", default)
    if units not in UNIT_SCALE[kind]:
        raise ValueError(f"{where}: {kind}.units must be one of {list(UNIT_SCALE[kind])}, got {units!r}")
    return str(units)


def _axis(text: object, label: str, where: str) -> tuple[int, float]:
    """'z' → (2, +1), '-x' → (0, −1)."""
    if not isinstance(text, str) or text.lstrip("+-") not in AXES or len(text) > 2:
        raise ValueError(f"{where}: {label} must be one of x, y, z, optionally signed (-z), got {text!r}")
    return AXES.index(text.lstrip("+-")), -1.0 if text.startswith("-") else 1.0


def topic_map_from_dict(doc: object, where: str = "topic map") -> TopicMap:
    """A TopicMap from the parsed YAML (missing keys take the defaults); ValueError names the key at fault."""
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected a mapping of accel, force, speed, frames, got {type(doc).__name__}")
    unknown = sorted(set(doc) - {"accel", "force", "speed", "frames", "max_gap_s", "reorder_s"})
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {unknown}; expected accel, force, speed, frames, max_gap_s, reorder_s"
        )
    accel = _section(doc, "accel", ("topic", "units"), where)
    force = _section(doc, "force", ("topic", "frame", "normal", "units"), where)
    speed = _section(doc, "speed", ("topic", "axes", "units"), where)
    frames = _section(doc, "frames", ("topic",), where)
    frame = force.get("frame")
    if frame is not None and not (isinstance(frame, str) and frame):
        raise ValueError(f"{where}: force.frame must be a frame id or null, got {frame!r}")
    normal_axis, normal_sign = _axis(force.get("normal", "z"), "force.normal", where)
    axes = speed.get("axes", ["x", "y"])
    if not (isinstance(axes, list) and axes and all(a in AXES for a in axes) and len(set(axes)) == len(axes)):
        raise ValueError(f"{where}: speed.axes must be a list of distinct axes among x, y, z, got {axes!r}")
    max_gap_s, reorder_s = doc.get("max_gap_s", 0.05), doc.get("reorder_s", 0.01)
    check_positive(f"{where}: max_gap_s", max_gap_s)
    check_positive(f"{where}: reorder_s", reorder_s)
    return TopicMap(
        accel_topic=accel.get("topic"),
        accel_units=_units(accel, "accel", "m/s^2", where),
        force_topic=force.get("topic"),
        force_frame=frame,
        normal_axis=normal_axis,
        normal_sign=normal_sign,
        force_units=_units(force, "force", "N", where),
        speed_topic=speed.get("topic"),
        speed_axes=tuple(AXES.index(a) for a in axes),
        speed_units=_units(speed, "speed", "m/s", where),
        frames_topic=frames.get("topic"),
        max_gap_s=float(max_gap_s),
        reorder_s=float(reorder_s),
    )


def load_topic_map(path: str | Path | None = None) -> TopicMap:
    """The topic map in YAML file `path` (None: the defaults, DEFAULT_TOPICS_FILE)."""
    import yaml

    path = Path(path) if path is not None else DEFAULT_TOPICS_FILE
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ValueError(f"topic map {path}: cannot read it ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"topic map {path}: not valid YAML ({exc})") from None
    return topic_map_from_dict(doc, f"topic map {path}")


def default_topics_text() -> str:
    """The default topic map file, as shown by --help."""
    return DEFAULT_TOPICS_FILE.read_text()
