"""Start the islanding node graph with native ROS 2 (`ros2 launch controlled_islanding islanding.launch.py`).

It mirrors controlled_islanding.graph.supervisor.GRAPH (same executables, same parameter files), which is what the
pip-only path (`controlled-islanding replay/demo`) starts; test_nodes_launch checks the two agree.
Play a bag into it with: ros2 run controlled_islanding bag_player --ros-args -p bag:=BAG

namespace:=area1 runs every node in /area1 (/area1/pmu/frames, /area1/breaker_command/set_armed, ...), so two
control areas share one domain, as `controlled-islanding replay --namespace` does; /diagnostics stays global.
clock:=/area1/clock makes them follow that area's own clock (default /clock), e.g. its bag player's:
ros2 run controlled_islanding bag_player --ros-args -r __ns:=/area1 -r /clock:=/area1/clock -p bag:=BAG
monitor:=true also starts the stability monitor (graph.supervisor.MONITOR), which then asks for islanding itself.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description():
    """Return the four pipeline nodes (and the monitor with monitor:=true), each with its config/<executable>.yaml."""
    config = os.path.join(get_package_share_directory('controlled_islanding'), 'config')
    use_sim_time = LaunchConfiguration('use_sim_time')
    sim = {'use_sim_time': use_sim_time}
    namespace = LaunchConfiguration('namespace')
    clock = [('/clock', LaunchConfiguration('clock'))]
    return LaunchDescription([
        DeclareLaunchArgument('use_sim_time', default_value='false', description='follow /clock from a bag player'),
        DeclareLaunchArgument('namespace', default_value='', description='run every node in this namespace'),
        DeclareLaunchArgument('clock', default_value='/clock', description='the clock topic use_sim_time follows'),
        DeclareLaunchArgument('monitor', default_value='false',
                              description='also start the stability monitor, which requests islanding itself'),
        Node(package='controlled_islanding', executable='pmu_ingestion', name='pmu_ingestion', output='screen',
             parameters=[os.path.join(config, 'pmu_ingestion.yaml'), sim], namespace=namespace,
             remappings=clock),
        Node(package='controlled_islanding', executable='coherency', name='coherency', output='screen',
             parameters=[os.path.join(config, 'coherency.yaml'), sim], namespace=namespace,
             remappings=clock),
        Node(package='controlled_islanding', executable='partitioning', name='partitioning', output='screen',
             parameters=[os.path.join(config, 'partitioning.yaml'), sim], namespace=namespace,
             remappings=clock),
        Node(package='controlled_islanding', executable='breaker_command', name='breaker_command', output='screen',
             parameters=[os.path.join(config, 'breaker_command.yaml'), sim], namespace=namespace,
             remappings=clock),
        Node(package='controlled_islanding', executable='stability_monitor', name='stability_monitor', output='screen',
             parameters=[os.path.join(config, 'stability_monitor.yaml'), sim], namespace=namespace,
             remappings=clock, condition=IfCondition(LaunchConfiguration('monitor'))),
    ])
