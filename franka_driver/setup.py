"""ament_python package franka_driver (entry points install to lib/franka_driver for ros2 run)."""

from setuptools import find_packages, setup

PACKAGE = "franka_driver"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="nf-control maintainers",
    maintainer_email="maintainers@nf-control.dev",
    description=open("package.xml").read().split("<description>")[1].split("</description>")[0],
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "franka_driver = franka_driver.stack:main",
            "nf_franka_stack = franka_driver.stack:main",
            "deploy_policy = franka_driver.deploy:main",
        ],
    },
)
