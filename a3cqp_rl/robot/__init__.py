"""Panda robot: MJCF assets, batched pytorch-kinematics model, datasheet limits and a batched MuJoCo simulator."""

from a3cqp_rl.robot.kinematics import Kinematics, PandaModel, build_chain_from_mjcf
from a3cqp_rl.robot.mjcf import DEFAULT_TOOL, PANDA_XML, TOOLS, compose_mjcf, mjcf_file, table_xml
from a3cqp_rl.robot.sim import PandaSim, SimState, mujoco_dynamics
from a3cqp_rl.robot.specs import PANDA_HOME, PANDA_LIMITS, PandaLimits

__all__ = ["Kinematics", "PandaModel", "build_chain_from_mjcf", "DEFAULT_TOOL", "PANDA_XML", "TOOLS", "compose_mjcf",
           "mjcf_file", "table_xml", "PandaSim", "SimState", "mujoco_dynamics", "PANDA_HOME", "PANDA_LIMITS", "PandaLimits"]
