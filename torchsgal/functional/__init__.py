"""Functional layer: every group operation on plain tensors (group matrices and tangent
vectors).  ``exp``/``log`` carry the custom autograd; ``exp_impl``/``log_impl`` are the same
maths differentiated by plain autograd (the test oracle for the custom backward)."""
from . import numerics, se2, se3, se23, sgal3, sim3, so2, so3
from ._blocking import unobserved

GROUPS = {"SO2": so2, "SE2": se2, "SO3": so3, "SE3": se3, "SE23": se23, "SGal3": sgal3, "Sim3": sim3}

__all__ = ["so2", "se2", "so3", "se3", "se23", "sgal3", "sim3", "numerics", "GROUPS", "unobserved"]
