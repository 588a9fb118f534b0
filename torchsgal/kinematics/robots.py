"""Standard-DH tables of example manipulators (joint variables add to theta or d).

Each factory builds a :class:`GDHChain` in ``dtype`` (float64 by default) on ``device``; the
joint tensors given to its methods must have that dtype and device (nothing is cast)."""
from __future__ import annotations

import math

import torch

from .gdh import GDHChain

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
