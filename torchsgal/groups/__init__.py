from .base import LieGroup
from .se3 import SE3
from .se23 import SE23
from .sgal3 import SGal3
from .so3 import SO3

__all__ = ["LieGroup", "SO3", "SE3", "SE23", "SGal3"]
