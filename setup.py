"""One ament_python package, `fluidlab_ros`, that also installs with plain pip.

`pip install .` puts the `fluidlab` command on PATH; a colcon build on a ROS 2 Jazzy machine installs the
same console scripts under lib/fluidlab_ros (setup.cfg) where `ros2 run` finds them.
"""
from setuptools import find_packages, setup

PACKAGE = "fluidlab_ros"

# Numerical dependencies are pinned so that results are reproducible.
INSTALL_REQUIRES = [
    "taichi==1.7.4",
    "numpy==2.4.6",
    "scipy==1.17.1",
    "trimesh==5.2.0",
    "rtree==1.4.1",
    "pillow==13.0.0",
    "gymnasium==1.4.0",
    "cma==4.5.0",
    "imageio-ffmpeg==0.8.1",  # ships the ffmpeg binary that encodes the MP4 videos
]

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Differentiable multi-material fluid simulation for robot trajectories, with a ROS 2 node",
    packages=find_packages(include=["fluidlab_core", "fluidlab_core.*", "fluidlab_ros", "fluidlab_ros.*"]),
    python_requires=">=3.11",
    install_requires=INSTALL_REQUIRES,
    package_data={"fluidlab_core.tasks": ["data/*.npz"]},
    extras_require={"test": ["pytest==9.2.0"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ],
    entry_points={"console_scripts": ["fluidlab = fluidlab_core.cli:main"]},
    zip_safe=False,
)
