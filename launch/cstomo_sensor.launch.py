"""Launch cstomo_sensor_node, optionally with a simulated board.

    ros2 launch cstomo_sensor cstomo_sensor.launch.py port:=/dev/cstomo
    ros2 launch cstomo_sensor cstomo_sensor.launch.py sim:=true        # board-sim on a pty, node on its link
    ros2 launch cstomo_sensor cstomo_sensor.launch.py config:=my.yaml namespace:=left_knee

The node's parameters come from ``config`` (keyed ``/**/cstomo_sensor``: any namespace); ``port``,
``sensor`` and ``estimator`` override it only when given (their default, empty, keeps the file's
value). ``sim``, ``sim_load_script``, ``config`` and ``namespace`` are for the launch itself. With
``sim:=true`` the simulated board, its link and the node's tare file live in a temporary directory of
this launch, removed when it ends. Arguments are plain strings: nothing in them is evaluated.
"""
import os
import shutil

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnShutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode

from cstomo_sensor.tools.common import launch_plan
from launch import LaunchDescription

ARGUMENTS = {  # name: (default, description)
    "port": ("", "serial URL of the board (default: the config file's port)"),
    "config": (None, "parameter file of the node"),
    "sim": ("false", "true: also start `cstomo board-sim` and read its pty link"),
    "sensor": ("", "sensor preset or YAML path (default: the config file's)"),
    "estimator": ("", "force estimator: linear or model (default: the config file's)"),
    "namespace": ("", "namespace of the node's topics"),
    "sim_load_script": ("", "with sim: load script CSV for the simulated board (default: built in)"),
}


def _setup(context):
    """The board (with ``sim``) and the node, from the arguments' values as plain strings."""
    args = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    overrides, board_cmd, work = launch_plan(args)
    actions = []
    if work is not None:
        actions.append(RegisterEventHandler(OnShutdown(on_shutdown=lambda *_: shutil.rmtree(work, ignore_errors=True))))
        actions.append(ExecuteProcess(cmd=board_cmd, output="screen"))
    actions.append(LifecycleNode(package="cstomo_sensor", executable="cstomo_sensor_node", name="cstomo_sensor",
                                 namespace=args["namespace"], output="screen",
                                 parameters=[args["config"], overrides]))
    return actions


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("cstomo_sensor"), "config", "cstomo_sensor.yaml")
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=config if default is None else default, description=desc)
         for name, (default, desc) in ARGUMENTS.items()]
        + [OpaqueFunction(function=_setup)])
