"""ament_python set-up for cstomo_sensor (also installs with plain pip into a virtual environment)."""
from glob import glob

from setuptools import find_packages, setup

package_name = "cstomo_sensor"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    # the default sensor's meshes (model/mesh.py): read by path, so the package is not zip-safe
    package_data={package_name: ["data/meshes/*.npz"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.rules") + glob("config/*.rviz")),
        ("share/" + package_name + "/config/sensors", glob("config/sensors/*.yaml")),
        ("share/" + package_name + "/scenes", glob("scenes/*.yaml")),
        ("share/" + package_name + "/scenes/devices", glob("scenes/devices/*.yaml")),  # the scenes' own sensors
        # the calibration example of docs/calibration.md: a bag and a frames/forces pair of a simulated device
        ("share/" + package_name + "/examples/calibration", glob("examples/calibration/*.csv")),
        ("share/" + package_name + "/examples/calibration/bag", glob("examples/calibration/bag/*")),
    ],
    python_requires=">=3.10",
    install_requires=["setuptools", "numpy", "scipy", "PyYAML", "pyserial"],
    extras_require={
        # Everything a workstation without ROS needs (make test installs this set).
        "full": ["pyvista", "pytetwild", "scikit-fem", "rosbags", "matplotlib"],
        # colcon and ament_package: test_colcon_install.py builds the package as a robot install does;
        # pytest-xdist: make test runs the suite on two workers.
        "test": ["pytest", "pytest-xdist", "hypothesis", "ruff", "colcon-core", "colcon-ros", "ros-kilted-ament-package"],
    },
    zip_safe=False,
    maintainer="cstomo_sensor developers",
    maintainer_email="cstomo@example.com",
    description="EIT force-direction sensor for a robot joint, as a ROS 2 node",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "cstomo = cstomo_sensor.scripts:cstomo",
            "cstomo_sensor_node = cstomo_sensor.scripts:node",
            "cstomo_sensor_host = cstomo_sensor.scripts:host",
        ],
    },
)
