"""Serial manipulators: chains from URDF, DH tables and pytorch-kinematics (pose, velocity,
acceleration, Jacobians as products of extended poses), GDH chains, and inverse kinematics."""
from .chain import KinematicChain
from .gdh import PRISMATIC, REVOLUTE, GDHChain, GDHState
from .ik import IKResult, inverse_kinematics
from .robots import URDF_ROBOTS, iiwa7, load_robot, panda, robot_urdf, scara, ur5
from .state import CONTINUOUS, ChainState, Joint
from .urdf import example_robot_data_dir, from_pk, from_urdf, parse_urdf

__all__ = ["GDHChain", "GDHState", "REVOLUTE", "PRISMATIC", "CONTINUOUS", "scara", "ur5", "iiwa7",
           "KinematicChain", "ChainState", "Joint", "from_urdf", "from_pk", "parse_urdf",
           "load_robot", "panda", "robot_urdf", "URDF_ROBOTS", "example_robot_data_dir",
           "inverse_kinematics", "IKResult"]
