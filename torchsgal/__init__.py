"""torchsgal: batched, differentiable SO(3), SE(3), SE_2(3) and SGal(3) for PyTorch (with SO(2),
SE(2) and Sim(3) on the same API)."""
from . import functional, interop, load, nn
from .groups import SE2, SE3, SE23, SO2, SO3, LieGroup, SGal3, Sim3

__version__ = "0.1.0"
GROUPS = (SO3, SE3, SE23, SGal3)  # the 3-D Galilean family
ALL_GROUPS = (SO2, SE2, SO3, SE3, SE23, SGal3, Sim3)  # GROUPS, the planar groups and Sim(3)

__all__ = ["SO2", "SE2", "SO3", "SE3", "SE23", "SGal3", "Sim3", "LieGroup", "GROUPS", "ALL_GROUPS",
           "functional", "interop", "load", "nn", "__version__"]
