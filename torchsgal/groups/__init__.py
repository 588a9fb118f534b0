import torch

from .base import LieGroup, _rebuild
from .se2 import SE2
from .se3 import SE3
from .se23 import SE23
from .sgal3 import SGal3
from .sim3 import Sim3
from .so2 import SO2
from .so3 import SO3

# torch.load(weights_only=True), the default since torch 2.6, rebuilds only allowlisted classes;
# a group element pickles as cls(matrix) (LieGroup.__reduce__), whose constructor checks the
# matrix's shape and dtype, so allowing the classes lets a checkpoint hold group elements and
# nothing more.  _rebuild (a subclass element with attributes) only rebuilds allowlisted
# LieGroup subclasses, after the same checks.
torch.serialization.add_safe_globals([SO2, SE2, SO3, SE3, SE23, SGal3, Sim3, _rebuild])

__all__ = ["LieGroup", "SO2", "SE2", "SO3", "SE3", "SE23", "SGal3", "Sim3"]
