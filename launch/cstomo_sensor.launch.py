"""Launch cstomo_sensor_node, optionally with a simulated board, its static transform and RViz2.

    ros2 launch cstomo_sensor cstomo_sensor.launch.py port:=/dev/cstomo
    ros2 launch cstomo_sensor cstomo_sensor.launch.py sim:=true rviz:=true     # board-sim on a pty, node, RViz
    ros2 launch cstomo_sensor cstomo_sensor.launch.py port:=/dev/cstomo namespace:=left_knee \
        frame_id:=left_knee_socket parent_frame:=left_shank z:=0.12 yaw:=1.5708
    ros2 launch cstomo_sensor cstomo_sensor.launch.py sensors:=config/sensors_example.yaml   # several sensors

The node's parameters come from ``config`` (keyed ``/**/cstomo_sensor``: any namespace); ``port``,
``sensor``, ``estimator``, ``frame_id``, ``calibration_file`` and ``tare_on_start`` override it only
when given (their default, empty, keeps the file's value). The others are for the launch itself:
``parent_frame`` and the pose ``x y z roll pitch yaw`` (metres, radians) start tf2_ros's
static_transform_publisher from that frame to the node's frame_id; ``sensors`` names a YAML list of
sensors instead of the one of the arguments (docs/robot.md); ``rviz:=true`` starts RViz2 on
``rviz_config`` rewritten for the launched sensors' topics. What is started is decided by
:func:`cstomo_sensor.tools.launching.launch_plan` (tested without launch), which also refuses the
launch, before anything starts, when an executable it would start is not installed (tf2_ros's
static_transform_publisher, rviz2, the node, the simulated board); this file only turns the plan into
actions. With ``sim:=true`` the simulated board, its link and the node's tare file live in
a temporary directory of this launch, removed when it ends. A node that exits with an error (a refused
parameter) ends the launch. Arguments are plain strings: nothing in
them is evaluated.
"""
import os
import shutil

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction, RegisterEventHandler, Shutdown
from launch.event_handlers import OnShutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

from cstomo_sensor.tools.launching import ARGUMENTS, NODE_NAME, launch_plan
from launch import LaunchDescription

_DEFAULT_FILES = {"config": "cstomo_sensor.yaml", "rviz_config": "cstomo_sensor.rviz"}  # in share/.../config


def _on_exit(node: str):
    """What node ``node`` exiting does: with an error (it refused its parameters, or failed) it ends the
    launch (launch says "was required: shutting down"); else its simulated board, transform and RViz
    would go on without it, silently. While the launch stops, any exit is launch's own business."""
    def on_exit(event, context):
        if event.returncode == 0 or context.is_shutdown:
            return None
        return [Shutdown(reason=f"{node} exited with code {event.returncode}")]
    return on_exit


def _setup(context):
    """The actions of the plan of the arguments' values (plain strings)."""
    plan = launch_plan({name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}, check=True)
    actions = []
    if plan.work is not None:
        work = plan.work
        actions.append(RegisterEventHandler(OnShutdown(on_shutdown=lambda *_: shutil.rmtree(work, ignore_errors=True))))
    for sensor in plan.sensors:
        if sensor.board is not None:
            actions.append(ExecuteProcess(cmd=sensor.board, output="screen"))
        actions.append(LifecycleNode(package="cstomo_sensor", executable="cstomo_sensor_node", name=NODE_NAME,
                                     namespace=sensor.namespace, output="screen",
                                     parameters=[*([sensor.config] if sensor.config else []), sensor.overrides],
                                     on_exit=_on_exit(sensor.node)))
        if sensor.transform is not None:
            actions.append(Node(package="tf2_ros", executable="static_transform_publisher", name=f"{NODE_NAME}_tf",
                                namespace=sensor.namespace, output="screen", arguments=sensor.transform.arguments()))
    if plan.rviz is not None:
        actions.append(Node(package="rviz2", executable="rviz2", name="rviz2", output="screen", arguments=plan.rviz))
    return actions


def generate_launch_description() -> LaunchDescription:
    share = os.path.join(get_package_share_directory("cstomo_sensor"), "config")
    return LaunchDescription(
        [DeclareLaunchArgument(name, description=desc,
                               default_value=os.path.join(share, _DEFAULT_FILES[name]) if default is None else default)
         for name, (default, desc) in ARGUMENTS.items()]
        + [OpaqueFunction(function=_setup)])
