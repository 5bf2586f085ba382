"""The node process: DDS memory settings, the heap settled before spinning, init, spin, Ctrl-C and shutdown.

Readers and writers allocate each DDS sample's buffer when it arrives and free it when it is taken
(Fast DDS history memory policy DYNAMIC, see `dds_memory_profile`): under rmw_fastrtps' default
(PREALLOCATED_WITH_REALLOC) every pooled buffer keeps the largest size it ever held, so a KEEP_LAST 1000
reader that now and then gets a frame of 10,000 PMUs grows towards 1000 x 720 kB.

Reliable writers send a heartbeat every 0.1 s while a reader has not acknowledged a sample (same profile; Fast
DDS's default is 3 s). A reader that misses a sample's first delivery asks for it again only after a heartbeat:
in three IEEE 14 fast replays, each of the 6 branch statuses played was acknowledged by every reader only after
0.6-3.0 s with 3 s (bag_player's acknowledgement wait), after 0.04-0.17 s with 0.1 s; a request, decision or
command lost live would be as late.
"""

from __future__ import annotations

import gc
import logging
import os
import sys
import tempfile
from collections.abc import Callable

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from controlled_islanding.ros.params import NodeSetupError


def settle_heap() -> None:
    """Move everything alive now out of the garbage collector's view.

    The libraries a node imports (scipy, scikit-learn, pypower) leave hundreds of thousands of objects; a
    full collection that walks them all stalls the node for tens of ms, in the middle of a request.
    """
    gc.collect()
    gc.freeze()


_DDS_MEMORY_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_reader profile_name="controlled_islanding_reader" is_default_profile="true">
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
  </data_reader>
  <data_writer profile_name="controlled_islanding_writer" is_default_profile="true">
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>100000000</nanosec></heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""


def dds_memory_profile() -> str | None:
    """Point Fast DDS at a profile with the DYNAMIC history memory policy; return the file to delete.

    rmw_fastrtps forces PREALLOCATED_WITH_REALLOC unless RMW_FASTRTPS_USE_QOS_FROM_XML is set, and takes the
    XML defaults only for what the ROS QoS does not set (history, depth, reliability and durability still
    come from TOPIC_QOS). A user who configured Fast DDS through either variable keeps their own setup.
    The file is private to this process and deleted once the node exists (Fast DDS reads it when the first
    participant is created).
    """
    if 'RMW_FASTRTPS_USE_QOS_FROM_XML' in os.environ or 'FASTRTPS_DEFAULT_PROFILES_FILE' in os.environ:
        return None
    fd, path = tempfile.mkstemp(prefix='controlled_islanding_fastdds_', suffix='.xml')
    with os.fdopen(fd, 'w') as handle:
        handle.write(_DDS_MEMORY_XML)
    os.environ['RMW_FASTRTPS_USE_QOS_FROM_XML'] = '1'
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = path
    return path


def _log_to_stderr() -> None:
    # The library code a node runs (sim/ in grid_sim) logs through `logging`; its lines go to the node's log.
    package = logging.getLogger('controlled_islanding')
    if not package.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter('%(message)s'))
        package.addHandler(handler)
        package.setLevel(logging.INFO)


def spin_node(factory: Callable[[], Node], args: list[str] | None = None,
              run: Callable[[Node, SingleThreadedExecutor], None] | None = None) -> int:
    """Init rclpy, build the node, spin it single-threaded until Ctrl-C or shutdown, then clean up.

    Args:
        factory: Builds the node; called after rclpy.init.
        args: Command line arguments (for --ros-args).
        run: What to do with the node and its executor instead of spinning forever (a node with an end,
            like the bag player).

    Returns:
        Process exit status: 0 after a clean stop, 1 when the node failed to start.

    """
    _log_to_stderr()
    profile = dds_memory_profile()
    rclpy.init(args=args)
    node = None
    status = 0
    try:
        node = factory()
        if profile is not None:
            os.unlink(profile)
            profile = None
        settle_heap()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        if run is None:
            executor.spin()
        else:
            run(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # Seen once in ~300 graph runs: a message take in flight when SIGINT shut the context down failed in
        # rclpy's C layer ("Unable to convert call argument") after the node's work was done. Only then is it
        # quiet; on a live context it is a real failure.
        if rclpy.ok():
            raise
    except (NodeSetupError, ParameterException) as exc:
        print(f'error: {type(exc).__name__}: {exc}' if isinstance(exc, ParameterException) else f'error: {exc}',
              flush=True)
        status = 1
    finally:
        if profile is not None:
            os.unlink(profile)
        if node is not None:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return status
