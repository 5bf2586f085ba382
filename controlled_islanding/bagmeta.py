"""What rosbags leaves for rosbag2's own tools to read in a bag's metadata.yaml.

rosbags writes `ros_distro: rosbags`; `ros2 bag` reads the distribution from that field, and our bags
hold Jazzy's message definitions and type hashes, so it is set to jazzy once the writer has closed. (The
copy of the metadata embedded in the MCAP file keeps rosbags' value: rosbag2 reads metadata.yaml.)
"""

from __future__ import annotations

import os
import re
from pathlib import Path

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
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(new)
    os.replace(tmp, path)
