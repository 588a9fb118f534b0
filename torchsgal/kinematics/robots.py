"""Example manipulators: standard-DH tables (:class:`GDHChain`) and real robots' URDF files.

Each factory builds its chain in ``dtype`` (float64 by default) on ``device``; the joint
tensors given to its methods must have that dtype and device (nothing is cast).  The URDF
robots come from the package ``example-robot-data`` (meshes are not read)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch

from .chain import KinematicChain
from .gdh import GDHChain
from .urdf import example_robot_data_dir, from_urdf

PI = math.pi


def scara(dtype=torch.float64, device=None) -> GDHChain:
    """The SCARA of Figure 4 of the mahony paper: revolute joints 1, 2 and 4, prismatic joint 3.
    Link lengths (the figure gives none): a1 = 0.4 m, a2 = 0.3 m, base height 0.5 m, tool
    offset 0.1 m."""
    return GDHChain(
        a=[0.4, 0.3, 0.0, 0.0], alpha=[0.0, PI, 0.0, 0.0], d=[0.5, 0.0, 0.0, 0.1],
        theta_offset=[0.0] * 4, joint_types="RRPR", dtype=dtype, device=device, name="scara",
    )


def ur5(dtype=torch.float64, device=None) -> GDHChain:
    """Universal Robots UR5, standard DH (the manufacturer's table)."""
    return GDHChain(
        a=[0.0, -0.425, -0.39225, 0.0, 0.0, 0.0],
        alpha=[PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0],
        d=[0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823],
        theta_offset=[0.0] * 6, joint_types="RRRRRR", dtype=dtype, device=device, name="ur5",
    )


def iiwa7(dtype=torch.float64, device=None) -> GDHChain:
    """KUKA LBR iiwa **14 R820** (not the iiwa 7 R800, despite the name), a 7-DoF arm,
    standard DH.

    The name is kept for compatibility (read its "7" as the seven joints); the table is the
    14 R820's, (d1, d3, d5, d7) = (0.36, 0.42, 0.40, 0.126) m (the 7 R800's d1, d3, d5 are
    0.34, 0.40, 0.40 m).
    """
    return GDHChain(
        a=[0.0] * 7,
        alpha=[-PI / 2, PI / 2, PI / 2, -PI / 2, -PI / 2, PI / 2, 0.0],
        d=[0.36, 0.0, 0.42, 0.0, 0.4, 0.0, 0.126],
        theta_offset=[0.0] * 7, joint_types="RRRRRRR", dtype=dtype, device=device, name="iiwa7",
    )


# ------------------------------------------------------------- real robots (URDF)
# name -> (URDF path under example-robot-data's robots folder, default end link(s))
URDF_ROBOTS = {
    "panda": ("panda_description/urdf/panda.urdf", "panda_hand_tcp"),
    "ur3": ("ur_description/urdf/ur3_robot.urdf", "tool0"),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "tool0"),
    "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
    "xarm7": ("xarm_description/urdf/xarm7.urdf", "link_eef"),
    "kinova": ("kinova_description/robots/kinova.urdf", "j2s6s200_end_effector"),
    "z1": ("z1_description/urdf/z1.urdf", "gripperStator"),
    "allegro": ("allegro_hand_description/urdf/allegro_right_hand.urdf",
                ("link_3.0_tip", "link_7.0_tip", "link_11.0_tip", "link_15.0_tip")),
}


def robot_urdf(name: str) -> Path:
    """The path of the URDF file of a robot shipped by ``example-robot-data``: one of
    ``URDF_ROBOTS`` ("panda", "ur3", "ur5", "ur10", "xarm7", "kinova", "z1", "allegro")."""
    if not isinstance(name, str):
        raise TypeError(f"name must be a robot name (a str), one of {sorted(URDF_ROBOTS)}, got "
                        f"{type(name).__name__} {name!r}")
    if name not in URDF_ROBOTS:
        raise ValueError(f"name must be one of {sorted(URDF_ROBOTS)}, got {name!r}")
    path = example_robot_data_dir() / URDF_ROBOTS[name][0]
    if not path.is_file():
        raise FileNotFoundError(f"example-robot-data has no {URDF_ROBOTS[name][0]} (looked in "
                                f"{path.parent})")
    return path


def load_robot(name: str, end_link: str | Sequence[str] | None = None,
               root_link: str | None = None, *,
               base=None, tool=None, dtype: torch.dtype = torch.float64,
               device=None) -> KinematicChain:
    """A :class:`KinematicChain` of a real robot from its URDF in ``example-robot-data``.

    ``end_link`` defaults to the robot's tool frame (``URDF_ROBOTS``: the Panda's
    ``panda_hand_tcp``, the UR arms' ``tool0``, the Allegro hand's four fingertips: a tree);
    ``root_link`` to the URDF's root.
    """
    path = robot_urdf(name)  # checks name
    # only None takes the default: "", [] or 0 are refused by from_urdf as any bad end link is
    end_link = URDF_ROBOTS[name][1] if end_link is None else end_link
    return from_urdf(path, end_link, root_link, base=base, tool=tool, dtype=dtype, device=device)


def panda(end_link: str = "panda_hand_tcp", dtype: torch.dtype = torch.float64,
          device=None) -> KinematicChain:
    """The Franka Emika Panda (7 revolute joints) from example-robot-data's URDF."""
    return load_robot("panda", end_link, dtype=dtype, device=device)
