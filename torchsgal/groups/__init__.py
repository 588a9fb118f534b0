from .base import LieGroup
from .se2 import SE2
from .se3 import SE3
from .se23 import SE23
from .sgal3 import SGal3
from .sim3 import Sim3
from .so2 import SO2
from .so3 import SO3

__all__ = ["LieGroup", "SO2", "SE2", "SO3", "SE3", "SE23", "SGal3", "Sim3"]
