"""ament_python package franka_driver: the Franka driver node and its torque loop (a library; the
program that composes it with the controller, ``nf_franka_stack``, is nf_bringup's)."""

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
)
