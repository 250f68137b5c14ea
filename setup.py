from glob import glob

from setuptools import find_packages, setup

package_name = "piezo_valve_ros"
script_dir = "$base/lib/" + package_name  # where `ros2 run` looks for the executables (as setup.cfg's [install])


def _develop_takes_script_dir() -> bool:
    """colcon --symlink-install runs `setup.py develop`, which must put the scripts in lib/<package>; newer
    setuptools dropped develop's script_dir (and a setup.cfg naming it breaks `pip install -e .` there)."""
    try:
        from setuptools.command.develop import develop
    except ImportError:
        return False
    return any(opt[0].rstrip("=") == "script-dir" for opt in getattr(develop, "user_options", []))


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "bench"]),
    package_data={package_name + ".runtime": ["fast_ack_profile.xml"]},   # read by Fast DDS from the installed package
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools", "numpy", "scipy", "rosbags>=0.11,<0.12", "threadpoolctl", "numba", "PyYAML"],
    extras_require={"plots": ["matplotlib"], "test": ["pytest"]},
    zip_safe=False,   # Fast DDS reads fast_ack_profile.xml as a file
    # install_scripts is in setup.cfg (the ROS convention); develop's script_dir only where setuptools has it
    options={"develop": {"script_dir": script_dir}} if _develop_takes_script_dir() else {},
    maintainer="piezo_valve_ros developers",
    maintainer_email="dev@piezo-valve.local",
    description="Piezo ring-bender valve: GPIM hysteresis model, inverse compensation, six controllers, ROS 2 nodes.",
    license="Apache-2.0",
    python_requires=">=3.10",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "valve_hardware = piezo_valve_ros.nodes.hardware:main",
            "valve_controller = piezo_valve_ros.nodes.controller:main",
            "valve_rig = piezo_valve_ros.cli.rig:main",
            "valve_composed = piezo_valve_ros.nodes.composed:main",
            "valve_identification = piezo_valve_ros.nodes.identification:main",
            "valve_identify = piezo_valve_ros.cli.identify:main",
            "valve_tune = piezo_valve_ros.cli.tune:main",
            "valve_record = piezo_valve_ros.cli.record:main",
            "valve_command = piezo_valve_ros.cli.command:main",
            "valve_plot = piezo_valve_ros.cli.plot:main",
            "valve_monitor = piezo_valve_ros.nodes.monitor:main",
        ],
        "piezo_valve_ros.backends": [
            "sim = piezo_valve_ros.backends:SimBackend",
        ],
    },
)
