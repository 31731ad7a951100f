"""fdi_ros: an ament_python package (``colcon build`` + ``ros2 run fdi_ros <node>`` on a real
ROS 2 install) that also installs with plain pip into the project venv (``scripts/setup.sh``)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "fdi_ros"

# One console script per node kind (``ros2 run fdi_ros <name>``) plus the ``fdi-ros`` CLI.
NODES = {
    "plant_node": "fdi_ros.nodes.plant_node:main",
    "preprocessor_node": "fdi_ros.nodes.preprocessor_node:main",
    "residual_node": "fdi_ros.nodes.residual_node:main",
    "model_host_node": "fdi_ros.nodes.model_host_node:main",
    "supervisor_node": "fdi_ros.nodes.supervisor_node:main",
    "recorder_node": "fdi_ros.nodes.recorder_node:main",
    "replayer_node": "fdi_ros.nodes.replayer_node:main",
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/scenarios", glob("config/scenarios/*.yaml")),
    ],
    python_requires=">=3.10",
    install_requires=["numpy", "scipy", "pyyaml", "rosbags", "mcap", "mcap-ros2-support",
                      "matplotlib", "tqdm", "psutil"],
    # `fdi-ros diagnose BAG... --engine dask / --cluster ADDRESS` (pinned in constraints.txt)
    extras_require={"dask": ["dask", "distributed"]},
    zip_safe=True,
    maintainer="fdi_ros maintainers",
    maintainer_email="maintainers@fdi-ros.dev",
    description="Model-based fault detection and isolation as a ROS 2 node graph",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{name} = {target}" for name, target in NODES.items()]
        + ["fdi-ros = fdi_ros.cli:main"],
    },
)
