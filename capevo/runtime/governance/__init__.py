"""Runtime governance R: every action an ECM proposes is checked against a fixed envelope Φ.

``R(a, Φ) = a | a′ | ⊥``: allow the action, replace it with a safe ``a′``, or reject it.

Quick use::

    from capevo.runtime.governance import Phi, hold_action, is_unsafe
    from capevo.runtime.state import SINGLE_PANDA

    phi = Phi.default()                      # the paper's envelope; or load_phi("my_phi.yaml")
    phi = Phi.for_task("pick")               # plus the task's scene: the runtime's default (capevo.runtime.envelope)
    govern = phi.governor(SINGLE_PANDA)      # once per run; enforce=False for governance-off
    trace.header["phi_hash"] = phi.hash
    governed, interventions = govern(state, proposed)
    if governed is None:                     # ⊥: hold still (or safe-abort)
        governed = hold_action(SINGLE_PANDA, last_executed)
"""

from __future__ import annotations

from capevo.runtime.governance.base import CONSTRAINTS, Check, Constraint, constraint_kinds, make, register
from capevo.runtime.governance.box import WorkspaceBox
from capevo.runtime.governance.cap import VelocityCap
from capevo.runtime.governance.closing_grip import ClosingGrip
from capevo.runtime.governance.contact_approach import ContactApproach
from capevo.runtime.governance.force import ContactForce
from capevo.runtime.governance.governor import GUARD, Governor, hold_action
from capevo.runtime.governance.guard import WorkspaceGuard
from capevo.runtime.governance.keep_clear import KeepClear
from capevo.runtime.governance.layouts import TWO_ARM_NO_GRIPPER, check_layout, layout_for
from capevo.runtime.governance.obstacle import ObstacleApproach
from capevo.runtime.governance.phi import Phi, load_phi, phi_for_task, phi_from_document
from capevo.runtime.governance.pose import ArmPose
from capevo.runtime.governance.proximity import ArmScene, Near, ProximitySensor, near_of
from capevo.runtime.governance.ramp import ForceRamp
from capevo.runtime.governance.reach import ReachLimit
from capevo.runtime.governance.records import GovernanceStats, Intervention, Verdict, verdict_of
from capevo.runtime.governance.separation import ArmSeparation
from capevo.runtime.governance.stopping import StoppingDistance
from capevo.runtime.governance.surface import SurfaceApproach
from capevo.runtime.governance.task_phi import TASK_GEOMETRY, TaskGeometry
from capevo.runtime.governance.unsafe import is_unsafe, unsafe_reasons
from capevo.runtime.governance.zone import Aabb, ForbiddenZone

__all__ = [
    "CONSTRAINTS",
    "GUARD",
    "TASK_GEOMETRY",
    "TWO_ARM_NO_GRIPPER",
    "Aabb",
    "ArmPose",
    "ArmScene",
    "ArmSeparation",
    "Check",
    "ClosingGrip",
    "Constraint",
    "ContactApproach",
    "ContactForce",
    "ForbiddenZone",
    "ForceRamp",
    "GovernanceStats",
    "Governor",
    "Intervention",
    "KeepClear",
    "Near",
    "ObstacleApproach",
    "Phi",
    "ProximitySensor",
    "ReachLimit",
    "StoppingDistance",
    "SurfaceApproach",
    "TaskGeometry",
    "VelocityCap",
    "Verdict",
    "WorkspaceBox",
    "WorkspaceGuard",
    "check_layout",
    "constraint_kinds",
    "hold_action",
    "is_unsafe",
    "layout_for",
    "load_phi",
    "make",
    "near_of",
    "phi_for_task",
    "phi_from_document",
    "register",
    "unsafe_reasons",
    "verdict_of",
]
