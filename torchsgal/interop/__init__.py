"""Converters between torchsgal and its peers: GTSAM, pypose, quaternion + translation poses
(ROS, TUM, Eigen) and Euler angles.

- ``interop.gtsam``: GTSAM objects (Rot2, Pose2, Rot3, Pose3, NavState, Gal3, Similarity3,
  Point2/3) to and from batched elements, and the maps of tangents, covariances and Jacobians
  between GTSAM's orders and ours.
- ``interop.pypose``: pypose LieTensors (SO3, SE3, Sim3 and their algebras), and the maps of
  covariances and Jacobians from pypose's left perturbation to our right one.
- ``interop.quaternion``: SE3 to and from ``(q, t)`` and 7-vectors ``[t, q]``, "wxyz" or "xyzw".
- ``interop.euler``: SO3 to and from Euler angles of a named sequence, intrinsic or extrinsic.

Importing this package imports neither GTSAM nor pypose: each converter imports its peer when
it runs, and raises ImportError naming the ``peers`` extra if the peer is missing.
"""
from . import euler, quaternion
from . import gtsam as gtsam  # re-exported (not in __all__)
from . import pypose as pypose
from .euler import as_euler, from_euler
from .quaternion import as_pose7, as_quaternion_translation, from_pose7, from_quaternion_translation

# the submodules gtsam and pypose are left out of __all__: a star import would shadow the peers
__all__ = ["quaternion", "euler", "from_euler", "as_euler", "from_pose7", "as_pose7",
           "from_quaternion_translation", "as_quaternion_translation"]
