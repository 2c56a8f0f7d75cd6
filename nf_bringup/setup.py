"""ament_python package nf_bringup (entry points install to lib/nf_bringup for ros2 run)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "nf_bringup"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),  # config/ -> the repository's config/
        (f"share/{PACKAGE}/config/tasks", glob("config/tasks/*.yaml")),  # the built-in task files
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="nf-control maintainers",
    maintainer_email="maintainers@nf-control.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "nf_sim_stack = nf_bringup.sim_stack:main",
            "nf_franka_stack = nf_bringup.franka_stack:main",
            "run_stack = nf_bringup.stack:main",
            "run_robot = nf_bringup.robot_run:main",
            "robot_state = nf_bringup.robot_state:main",
            "fleet_view = nf_bringup.fleet_view:main",
        ],
    },
)
