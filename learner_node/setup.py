"""ament_python package learner_node (entry points install to lib/learner_node for ros2 run)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "learner_node"

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
            "flow_selfcheck = learner_node.analysis.selfcheck:main",
            "train = learner_node.train_cli:main",
            "learner = learner_node.node:main",
            "nf_report = learner_node.analysis.report:main",
            "nf_compare = learner_node.analysis.compare:main",
            "deploy_policy = learner_node.deploy:main",
        ],
    },
)
