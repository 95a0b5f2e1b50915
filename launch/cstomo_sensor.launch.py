"""Launch cstomo_sensor_node, optionally with a simulated board.

    ros2 launch cstomo_sensor cstomo_sensor.launch.py port:=/dev/cstomo
    ros2 launch cstomo_sensor cstomo_sensor.launch.py sim:=true        # board-sim on a pty, node on its link
    ros2 launch cstomo_sensor cstomo_sensor.launch.py config:=my.yaml namespace:=left_knee

Arguments that are node parameters (``port``, ``sensor``, ``estimator``) override the ``config``
file; ``sim``, ``config`` and ``namespace`` are for the launch itself.
"""
import os
import tempfile

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import LifecycleNode

from launch import LaunchDescription

SIM_LINK = "/tmp/cstomo_sim"
# The simulated board's default load script (time,fx,fy,fz in s and N, wrench frame): unloaded for
# the tare, then pressing straight down, tilted towards +x, towards +y, and released (held until the launch stops).
SIM_LOAD = "time,fx,fy,fz\n0,0,0,0\n3,0,0,-20\n6,10,0,-15\n9,0,10,-15\n12,0,0,0\n"


def _board_sim(context):
    """``cstomo board-sim`` on a pty behind SIM_LINK, playing ``sim_load_script`` (or SIM_LOAD)."""
    script = LaunchConfiguration("sim_load_script").perform(context)
    if not script:
        fd, script = tempfile.mkstemp(prefix="cstomo_sim_load_", suffix=".csv")
        with os.fdopen(fd, "w") as f:
            f.write(SIM_LOAD)
    sensor = LaunchConfiguration("sensor").perform(context)
    return [ExecuteProcess(cmd=["cstomo", "board-sim", "--sensor", sensor, "--rate", "200", "--link", SIM_LINK,
                                "--load-script", script], output="screen")]


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("cstomo_sensor")
    sim = LaunchConfiguration("sim")
    port = LaunchConfiguration("port")
    sensor = LaunchConfiguration("sensor")
    return LaunchDescription([
        DeclareLaunchArgument("port", default_value="/dev/cstomo", description="serial URL of the board"),
        DeclareLaunchArgument("config", default_value=os.path.join(share, "config", "cstomo_sensor.yaml"),
                              description="parameter file of the node"),
        DeclareLaunchArgument("sim", default_value="false",
                              description="true: also start `cstomo board-sim` and read its pty link"),
        DeclareLaunchArgument("sensor", default_value="cuboid_joint", description="sensor preset or YAML path"),
        DeclareLaunchArgument("estimator", default_value="linear", description="force estimator: linear or model"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the node's topics"),
        DeclareLaunchArgument("sim_load_script", default_value="",
                              description="with sim: load script CSV for the simulated board (default: built in)"),
        OpaqueFunction(function=_board_sim, condition=IfCondition(sim)),
        LifecycleNode(
            package="cstomo_sensor",
            executable="cstomo_sensor_node",
            name="cstomo_sensor",
            namespace=LaunchConfiguration("namespace"),
            output="screen",
            parameters=[
                LaunchConfiguration("config"),
                {
                    "port": PythonExpression(["'", SIM_LINK, "' if '", sim, "'.lower() in ('true', '1') else '", port, "'"]),
                    "sensor": sensor,
                    "estimator": LaunchConfiguration("estimator"),
                },
            ],
        ),
    ])
