"""ament_python package nf_controller_node (entry points install to lib/nf_controller_node for ros2 run)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "nf_controller_node"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="nf-control maintainers",
    maintainer_email="maintainers@nf-control.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "nf_controller = nf_controller_node.node:main",
        ],
    },
)
