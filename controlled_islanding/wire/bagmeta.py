"""What rosbag2's own tools read in a bag's metadata: the offered QoS of each topic, and the distribution.

`ros2 bag play` offers each topic with the QoS recorded for it, and plays a topic with none as volatile,
which our transient-local readers never match; `qos_profile` turns a live QoS into the record. rosbags
writes `ros_distro: rosbags`; `ros2 bag` reads the distribution from that field, and our bags
hold Jazzy's message definitions and type hashes, so it is set to jazzy once the writer has closed. (The
copy of the metadata embedded in the MCAP file keeps rosbags' value: rosbag2 reads metadata.yaml.)
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from controlled_islanding import atomic

ROS_DISTRO = 'jazzy'
_DISTRO_LINE = re.compile(r'^(\s*ros_distro:\s*)\S+\s*$', re.MULTILINE)


class BagMetaError(ValueError):
    """A bag's metadata.yaml is missing or has no ros_distro field."""


def set_ros_distro(bag: Path, distro: str = ROS_DISTRO) -> None:
    """Set ros_distro in BAG/metadata.yaml, replacing the file atomically.

    Raises:
        BagMetaError: No metadata.yaml, or no ros_distro line in it.

    """
    path = Path(bag) / 'metadata.yaml'
    try:
        text = path.read_text()
    except OSError as exc:
        raise BagMetaError(f'{path}: cannot read it: {exc}') from exc
    new, n = _DISTRO_LINE.subn(lambda m: m.group(1) + distro, text, count=1)
    if n != 1:
        raise BagMetaError(f'{path}: no ros_distro field')
    atomic.write_text(path, new)


def qos_profile(qos: Any) -> Qos:
    """Return the rosbags record of an rclpy QoSProfile (rclpy's enums have rosbag2's values)."""
    def duration(d: Any) -> QosTime:
        sec, nsec = divmod(int(d.nanoseconds), 1_000_000_000)
        return QosTime(sec, nsec)

    def enum(cls: type, policy: Any) -> Any:
        try:
            return cls(int(policy))
        except ValueError:
            return cls(0)  # "system default": a value rosbag2 reads, where a middleware reports one it cannot

    return Qos(history=enum(QosHistory, qos.history), depth=int(qos.depth),
               reliability=enum(QosReliability, qos.reliability), durability=enum(QosDurability, qos.durability),
               deadline=duration(qos.deadline), lifespan=duration(qos.lifespan),
               liveliness=enum(QosLiveliness, qos.liveliness),
               liveliness_lease_duration=duration(qos.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions))


def other_definitions(connections: Any, store: Any) -> list[str]:
    """Name the connections recorded with a definition of their type other than `store`'s, by type hash.

    Their CDR bytes do not decode as this package's type: published raw they fail in every subscriber
    (a bag recorded before a message gained a field). A connection with no RIHS01 hash, or of a type the
    store does not know, is not judged.

    Returns:
        '<topic> (<type>)' for each such connection.

    """
    out = []
    for c in connections:
        digest = getattr(c, 'digest', '') or ''
        if digest.startswith('RIHS01_') and c.msgtype in store.fielddefs \
                and store.hash_rihs01(c.msgtype) != digest:
            out.append(f'{c.topic} ({c.msgtype})')
    return out


def unreadable(bag: str | Path, exc: BaseException) -> str:
    """Say why rosbags could not read `bag`, naming the file at fault: rosbags' own messages name neither.

    Args:
        bag: The path given as a bag: a rosbag2 folder (metadata.yaml and its storage files), or an .mcap file.
        exc: What rosbags raised opening or reading it.

    """
    import yaml

    path = Path(bag)
    if not path.exists():
        return f'{path} does not exist'
    if path.is_file():
        return f'truncated or corrupt MCAP file {path}: {exc}' if path.suffix == '.mcap' else \
            f'{path} is a file, not a rosbag2 bag folder: {exc}'
    meta = path / 'metadata.yaml'
    if not meta.is_file():
        return f'{path} is not a rosbag2 bag: it holds no metadata.yaml'
    try:
        files = [path / f for f in yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
                 ['relative_file_paths']]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return (f'{meta}: cannot read it as rosbag2 metadata (no rosbag2_bagfile_information with '
                f'relative_file_paths; rosbags: {exc})')
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        return f'{path}: its metadata.yaml names {", ".join(missing)}, which is not in the folder'
    mcaps = [f for f in files if f.suffix == '.mcap']
    if len(mcaps) == 1:
        return f'truncated or corrupt MCAP file {mcaps[0]}: {exc}'
    return f'{path}: cannot read it as a rosbag2 bag (one of {", ".join(f.name for f in files)} is corrupt?): {exc}'
