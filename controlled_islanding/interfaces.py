"""The project's message types for rosbags, built from the .msg files in msg_schemas/.

The same files are compiled for rclpy by tools/setup.sh, so live topics and bags
share one definition (and one RIHS01 type hash).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

PACKAGE = 'controlled_islanding_msgs'


class InterfacesError(RuntimeError):
    """The msg_schemas/ definitions cannot be found or parsed."""


def schema_dir() -> Path:
    """Return the directory holding msg/ and srv/ of controlled_islanding_msgs.

    Returns:
        The source tree's msg_schemas/ in a checkout, else the copy installed
        under share/controlled_islanding/msg_schemas.

    Raises:
        InterfacesError: Neither location exists.

    """
    here = Path(__file__).resolve().parent
    candidates = [here.parent / 'msg_schemas']
    if len(here.parents) > 3:  # installed: <prefix>/lib/pythonX.Y/site-packages/controlled_islanding
        candidates.append(here.parents[3] / 'share' / 'controlled_islanding' / 'msg_schemas')
    for candidate in candidates:
        if (candidate / 'msg').is_dir():
            return candidate
    raise InterfacesError(f'msg_schemas/ not found; looked in {", ".join(map(str, candidates))}')


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
