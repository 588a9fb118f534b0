"""Functional layer: every group operation on plain tensors (group matrices and tangent
vectors).  ``exp``/``log`` carry the custom autograd; ``exp_impl``/``log_impl`` are the same
maths differentiated by plain autograd (the test oracle for the custom backward)."""
from . import numerics, se3, se23, sgal3, so3

GROUPS = {"SO3": so3, "SE3": se3, "SE23": se23, "SGal3": sgal3}

__all__ = ["so3", "se3", "se23", "sgal3", "numerics", "GROUPS"]
