"""Robot descriptions shipped with the package: `<robot>/<robot>.urdf` (kinematics), `<robot>/limits.json`
(joint, torque and Cartesian limits), `<robot>/inertials.json` (link masses, centres of mass, inertias and the
default payload), `collision.json` (the links' capsules and self-collision pairs, both arms) and
`mounting.json` (each task's scene pose and table height).

`robot_models` is a package directory so that the data files install with `pip install .` (package_data)
and are found from the installed package with the functions below; nothing reads them by a path relative to
the source tree.
"""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent
ROBOTS = ("fr3", "panda")  # fr3 is the default arm


def _check(robot: str) -> str:
    if robot not in ROBOTS:
        raise ValueError(f"unknown robot model {robot!r}: known models are {', '.join(ROBOTS)}")
    return robot


def urdf_path(robot: str = "fr3") -> Path:
    """The arm's URDF (7 revolute joints `<robot>_joint1..7`, links `<robot>_link0..8`, flange `<robot>_link8`)."""
    return ROOT / _check(robot) / f"{robot}.urdf"


def limits_path(robot: str = "fr3") -> Path:
    return ROOT / _check(robot) / "limits.json"


def inertials_path(robot: str = "fr3") -> Path:
    return ROOT / _check(robot) / "inertials.json"


def collision_path() -> Path:
    return ROOT / "collision.json"


def mounting_path() -> Path:
    return ROOT / "mounting.json"
