"""A3CQP controller: tasks (IK, AC, FC, JC), limits (viable joint bounds, wrench box, friction pyramid), QP + torque."""

from a3cqp_rl.control.context import N_QDD, N_VARS, N_WRENCH, ControlContext
from a3cqp_rl.control.controller import (A3CQPController, ControllerOptions, ControlOutput,
                                         wrench_from_joint_torques)
from a3cqp_rl.control.hierarchy import Hierarchy, level_from_selector, levels_from_selectors, solve_cascade
from a3cqp_rl.control.limits import (FrictionPyramid, Inequality, JointLimitsViability, Limit, TorqueLimits,
                                     WrenchBox,
                                     joint_acceleration_bounds)
from a3cqp_rl.control.tasks import (Admittance, CartesianAccelerationRegularizer, CartesianIK, ForceControl,
                                    JointCentering, Residual, Task)

__all__ = ["N_QDD", "N_VARS", "N_WRENCH", "ControlContext", "A3CQPController", "ControllerOptions", "ControlOutput",
           "wrench_from_joint_torques", "FrictionPyramid", "Inequality", "JointLimitsViability", "Limit", "WrenchBox",
           "joint_acceleration_bounds", "TorqueLimits", "Admittance", "CartesianAccelerationRegularizer", "CartesianIK", "ForceControl", "JointCentering", "Residual",
           "Task", "Hierarchy", "level_from_selector", "levels_from_selectors", "solve_cascade"]
