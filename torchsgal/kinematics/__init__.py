"""Serial manipulators as Generalised Denavit-Hartenberg chains of extended poses (SE_2(3))."""
from .gdh import PRISMATIC, REVOLUTE, GDHChain, GDHState
from .robots import iiwa7, scara, ur5

__all__ = ["GDHChain", "GDHState", "REVOLUTE", "PRISMATIC", "scara", "ur5", "iiwa7"]
