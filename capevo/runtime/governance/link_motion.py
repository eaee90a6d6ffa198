"""How an action moves a point on an arm's link: the row ``contact_approach`` brakes a link pair along.

The proximity sensor can sense an arm's wrist links as well as its hand
(:meth:`~capevo.runtime.governance.proximity.ProximitySensor.for_robots`, ``wrist_links``). A
point on the hand moves rigidly with the end effector, so its closing speed along a pair's
direction ``n`` follows from the action's translation. A point on link 5 or 6 does not: under
robosuite's operational-space controller (OSC) it moves as the joints that realise the commanded
end-effector motion move it. Measured on the AM baseline's T1 policy (``results/cpu-small``,
seed 2000042007): twisting the hand by 0.1-0.2 per step drove the forearm (link 5) into the bin
at 315 N while the hand itself moved away from everything; braking the hand's own motion along
the pair still let it through at 463 N.

For a point ``p`` on body ``b`` of arm ``i`` and a unit direction ``n`` (from the link towards the
other geom), :meth:`LinkMotion.row` gives ``g`` (6 floats) with ``g · a`` the closing speed of
``p`` along ``n`` in the action's translation units, for the pose part ``a`` of arm ``i``'s
action. It follows the controller: OSC turns the commanded end-effector twist
``x = S a`` (``S`` the controller's ``output_max``: metres and radians per action unit) into
joint motion through the dynamically consistent inverse of the end-effector Jacobian,
``J̄ = M⁻¹ Jᵀ (J M⁻¹ Jᵀ)⁻¹`` (``M`` the arm's joint-space inertia, as robosuite's OSC uses it),
so ``p`` moves by ``J_p J̄ S a`` and ``g = nᵀ J_p J̄ S / S_t`` (``S_t`` the translation scale, so
that a point on the hand gets ``g = (n, (r × n) · S_r / S_t)``, the rigid motion).
What this leaves out: OSC's null-space posture term, which moves the elbow without any action
(it is not the action's doing, so no edit of the action can brake it), and the dynamics of the
step (the row is the first-order, quasi-static motion).

Invariants:
1. For a point on the end-effector body itself the row is the rigid motion: translation
   components ``n`` and rotation components ``(r × n) · S_r / S_t`` (to rounding), ``r`` the point
   relative to the end-effector site.
2. :meth:`LinkMotion.row` reads ``MjData`` only; it never steps or changes the simulator.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

LinkRow = tuple[float, float, float, float, float, float]
"""Closing speed per action unit of each of an arm's six pose components (see the module docstring)."""


@dataclass(frozen=True, slots=True)
class ArmJoints:
    """What :class:`LinkMotion` needs of one arm."""

    site: int
    """The end-effector site (where OSC's commanded twist acts)."""
    dofs: tuple[int, ...]
    """The arm's joint velocity indices in ``MjData.qvel``."""
    scale: tuple[float, ...]
    """OSC's ``output_max`` for the six pose components: metres, then radians, per action unit."""


class LinkMotion:
    """Rows of the closing speed of link points under an OSC_POSE action (module docstring).

    All linear algebra is MuJoCo's own (``mj_solveM`` on the factorised inertia the step already
    computed, and a 6 x 6 Cholesky): numpy's LAPACK calls cost 40-50 µs each here, more than the
    rest of a row. The inertia is the whole model's, where robosuite's OSC inverts the arm's
    block of it; the two differ by the fingers' coupling to the wrist.
    """

    def __init__(self, model: Any, data: Any, arms: Sequence[ArmJoints]) -> None:
        import mujoco  # here, not at module level: governance itself does not need MuJoCo

        self._mj = mujoco
        self.model, self.data = model, data
        self._arms = tuple(arms)
        nv = model.nv
        self._jacp = np.zeros((3, nv))
        self._m_inv_jac = np.zeros((6, nv))
        self._w = np.zeros((1, nv))
        self._m_inv_w = np.zeros((1, nv))
        self._g = np.zeros(6)
        # Per arm: (simulator time, J, Cholesky factor of J M⁻¹ Jᵀ, S / S_t) for that time.
        self._osc: list[tuple[float, np.ndarray, np.ndarray, np.ndarray] | None] = [None] * len(self._arms)

    def _arm_osc(self, arm: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """The end-effector Jacobian ``J`` of ``arm`` now, the Cholesky factor of ``J M⁻¹ Jᵀ`` and
        the action scale per translation unit."""
        d = self.data
        cached = self._osc[arm]
        if cached is not None and cached[0] == d.time:
            return cached
        a = self._arms[arm]
        mj, m = self._mj, self.model
        jac = np.zeros((6, m.nv))
        mj.mj_jacSite(m, d, jac[:3], jac[3:], a.site)
        mj.mj_solveM(m, d, self._m_inv_jac, jac)
        lam_inv = jac @ self._m_inv_jac.T
        mj.mju_cholFactor(lam_inv, 1e-12)
        scale = np.asarray(a.scale, dtype=np.float64)
        out = (float(d.time), jac, lam_inv, scale / scale[0])
        self._osc[arm] = out
        return out

    def row(self, arm: int, body: int, point: Sequence[float], n: Sequence[float]) -> LinkRow:
        """``g`` for world point ``point`` on ``body`` of ``arm`` and unit direction ``n``.

        ``g = nᵀ J_p J̄ S / S_t`` with ``J̄ = M⁻¹ Jᵀ (J M⁻¹ Jᵀ)⁻¹``, computed as
        ``(J M⁻¹ J_pᵀ n)ᵀ (J M⁻¹ Jᵀ)⁻¹`` (both inverses symmetric), scaled per component.
        """
        mj, m, d = self._mj, self.model, self.data
        _, jac, chol, scale = self._arm_osc(arm)
        mj.mj_jac(m, d, self._jacp, None, np.asarray(point, dtype=np.float64), body)
        np.dot(np.asarray(n, dtype=np.float64), self._jacp, out=self._w[0])
        mj.mj_solveM(m, d, self._m_inv_w, self._w)
        u = jac @ self._m_inv_w[0]
        mj.mju_cholSolve(self._g, chol, u)
        g = (self._g * scale).tolist()
        return (g[0], g[1], g[2], g[3], g[4], g[5])
