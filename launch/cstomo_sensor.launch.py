"""Launch cstomo_sensor_node, optionally with a simulated board.

    ros2 launch cstomo_sensor cstomo_sensor.launch.py port:=/dev/cstomo
    ros2 launch cstomo_sensor cstomo_sensor.launch.py sim:=true        # board-sim on a pty, node on its link
    ros2 launch cstomo_sensor cstomo_sensor.launch.py config:=my.yaml namespace:=left_knee

Arguments that are node parameters (``port``, ``sensor``, ``estimator``) override the ``config``
file; ``sim``, ``config`` and ``namespace`` are for the launch itself.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import LifecycleNode

SIM_LINK = "/tmp/cstomo_sim"


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
        ExecuteProcess(
            cmd=["cstomo", "board-sim", "--sensor", sensor, "--rate", "200", "--link", SIM_LINK,
                 "--load-script", os.path.join(share, "scenes", "sim_load.csv")],
            condition=IfCondition(sim),
            output="screen",
        ),
        LifecycleNode(
            package="cstomo_sensor",
            executable="cstomo_sensor_node",
            name="cstomo_sensor",
            namespace=LaunchConfiguration("namespace"),
            output="screen",
            parameters=[
                LaunchConfiguration("config"),
                {
                    "port": PythonExpression(["'", SIM_LINK, "' if '", sim, "' == 'true' else '", port, "'"]),
                    "sensor": sensor,
                    "estimator": LaunchConfiguration("estimator"),
                },
            ],
        ),
    ])
