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
    "pin==4.1.0",  # Pinocchio: URDF kinematics for the execution pipeline (fluidlab_ros)
    "ruckig==0.19.4",  # jerk-limited smoothing at the control rate
    "matplotlib==3.11.2",  # the replay report's plots
]

# example-robot-data (414 MB of meshes) is only the Panda URDF that tests/test_pipeline.py cross-checks
# robot_models/ against; it is a test extra, not a runtime dependency.
# pytest-xdist runs the test files in two processes, overlapping Taichi compilation (README).
# mcap: an MCAP reader independent of rosbags, to check the recordings (fluidlab_ros.recording also needs it at
# run time: requirements-ros.txt).
# colcon: tests/ros/test_colcon_build.py builds the repository with colcon as a ROS 2 Jazzy machine would. Only
# what that build uses, each pinned (colcon-ros pulls in the others unpinned): colcon-core 0.21.3 itself depends on
# pytest-cov, pytest-repeat and pytest-rerunfailures, which stay inactive unless their options are given.
COLCON = ["colcon-core==0.21.3", "colcon-ros==0.5.0", "colcon-python-setup-py==0.2.9", "colcon-cmake==0.2.30",
          "colcon-library-path==0.2.1", "colcon-pkg-config==0.1.0", "colcon-recursive-crawl==0.2.3",
          "colcon-test-result==0.3.8", "colcon-bash==0.5.0", "colcon-package-selection==0.2.10",
          "colcon-package-information==0.4.1"]
# ray: the optimiser benchmark's job scheduler (fluidlab_core/benchmark.py; without it runs go to a process pool).
BENCH = ["ray==2.60.0"]
# phiflow: bench/bench_gas.py times PhiFlow's smoke plume beside ours (not needed by the package or its tests).
PHIFLOW = ["phiflow==3.4.0", "phiml==1.16.1"]
# rl: the benchmark's SAC and PPO baselines (fluidlab_core/optim/rl.py). torch 2.13.0 is pinned to its CPU build
# (about 750 MB installed; `pip install torch==2.13.0` takes the CPU wheel where one is on disk). torch needs
# setuptools >= 77.0.3 and colcon-core < 80: 79.0.1 satisfies both.
RL = ["torch==2.13.0", "stable-baselines3==2.9.2", "setuptools==79.0.1"]
TEST_REQUIRES = ["pytest==9.2.0", "pytest-xdist==3.8.0", "example-robot-data==6.0.0", "mcap==1.6.0", *COLCON, *BENCH,
                 *RL]

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Differentiable multi-material fluid simulation for robot trajectories, with a ROS 2 node",
    packages=find_packages(include=["fluidlab_core", "fluidlab_core.*", "fluidlab_ros", "fluidlab_ros.*",
                                    "robot_models"]),
    # robot_models is a package directory: its URDFs, limits and mountings install with it and are found
    # through robot_models.urdf_path() / limits_path() / mounting_path(), from a wheel as from the source tree.
    package_data={"robot_models": ["*.json", "*/*.urdf", "*/*.json", "README.md"],
                  "fluidlab_core.tasks": ["data/*.npz"]},
    python_requires=">=3.11",
    install_requires=INSTALL_REQUIRES,
    extras_require={"test": TEST_REQUIRES, "bench": [*BENCH, *RL, *PHIFLOW], "rl": RL},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        # `ros2 launch fluidlab_ros sim_node.launch.py` looks in share/fluidlab_ros/launch
        (f"share/{PACKAGE}/launch", ["launch/sim_node.launch.py"]),
    ],
    entry_points={"console_scripts": ["fluidlab = fluidlab_core.cli:main",
                                    "sim_node = fluidlab_ros.sim_node:main",
                                    "command_monitor = fluidlab_ros.monitor:main"],
                  # sub-commands of `fluidlab` from packages that fluidlab_core must not import (cli.py)
                  "fluidlab.commands": ["replay = fluidlab_ros.cli:register"]},
    zip_safe=False,
)
