"""The project's message types for rosbags, built from the .msg files in msg_schemas/.

The same files are compiled for rclpy by tools/setup.sh, so live topics and bags
share one definition (and one RIHS01 type hash).
"""

from __future__ import annotations

from functools import lru_cache

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from controlled_islanding.locations import schema_dir

PACKAGE = 'controlled_islanding_msgs'


class InterfacesError(RuntimeError):
    """The msg_schemas/ definitions cannot be parsed."""


def msg_type_name(name: str) -> str:
    """Return the full ROS 2 type name of a message of this package, e.g. PmuFrame."""
    return f'{PACKAGE}/msg/{name}'


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """Return a Jazzy typestore with every controlled_islanding_msgs message registered.

    Raises:
        InterfacesError: A .msg file does not parse.

    """
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted((schema_dir() / 'msg').glob('*.msg')):
        try:
            types.update(get_types_from_msg(path.read_text(), msg_type_name(path.stem)))
        except Exception as exc:  # rosbags raises several parser exception types
            raise InterfacesError(f'{path}: {exc}') from exc
    store.register(types)
    return store
