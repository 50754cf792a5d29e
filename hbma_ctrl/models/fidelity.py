"""The fidelity ladder: one casadi plant model per scene type, each adding only what the scene needs.

=================  ==================  ===================================================================
fidelity           differential state  when
=================  ==================  ===================================================================
``free``           h1                  no load: free inflation; h2 = 0 and F = 0 by construction
exact ``free``     h1                  free inflation with the exact membrane's pressure and volume
                                       (:mod:`hbma_ctrl.models.fidelity_exact`): tables of
                                       :mod:`hbma_ctrl.models.exact` instead of the spherical cap
``quasi_static``   m (+ h1, h2 alg.)   dead load on a guided platform, the paper's quasi-static model:
                                       resting, lift-off, contact at F = m_L g, touch-down; a
                                       snap-through is a jump to the far branch at constant gas mass
``platform``       m, z, v (+ h1 alg.) the platform has mass and damping (m_L z'' = F - m_L g - c z'):
                                       snap-through is a real, fast transient; the platform may even
                                       leave the membrane (airborne) and land again
exact loaded       as above            ``quasi_static`` / ``platform`` with the exact flat-plate contact
                                       (:mod:`hbma_ctrl.models.fidelity_exact`): the cap's chart, the
                                       exact law as tabulated ratios (:mod:`hbma_ctrl.models.exact_tables`)
=================  ==================  ===================================================================

The simulator's ``exact`` rung (:func:`hbma_ctrl.models.fidelity_exact.make_exact`) is the exact
platform model with a load and the exact free inflation without one. The rungs here take the membrane
law as a hook (:meth:`Fidelity.contact_law`, :meth:`Fidelity.flat_h1`; the cap's by default), which
the exact rungs override.

Why these states. The gas mass ``m`` is the natural, drift-free state (the gas law): the gas law fixes
``G(h1, h2) = (p + p_env) V = m R T``. The (h1, h2) chart is singular at the flat origin (p ~ h1^3
along the flat membrane), so wherever the membrane can be flat (resting) the gas mass carries the
state and (h1, h2) are algebraic, found from the gas law and the contact condition. In free
inflation ``dG/dh1 >= p_env dV/dh1 > 0`` everywhere, so h1 alone is a regular state.

Algebraic variables are carried in the state vector (``x = [m, h1, h2]`` or ``[m, h1, z, v]``), with
their index-reduced derivatives, so explicit integrators see an ODE; the simulator projects them
back onto the constraints after every step (:meth:`Fidelity.project`), which is exact for the
constraint and leaves the gas mass untouched.

Every fidelity exposes casadi Functions with parameters as inputs (``theta``, see
:class:`hbma_ctrl.core.physics.ParamSpace`), so one Function serves a batch of trials, the EKF (Jacobians)
and the NMPC (discretised dynamics).
"""

from __future__ import annotations

from functools import cached_property

import casadi as ca
import numpy as np

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.materials import Material
from hbma_ctrl.core.validation import did_you_mean

__all__ = ["OUTPUTS", "Fidelity", "FreeInflation", "QuasiStatic", "DynamicPlatform",
           "FIDELITIES", "make_fidelity", "MODE_REST", "MODE_MOVING", "cap_law", "shape_jacobian",
           "pressure_det", "fixed_step"]

#: names of the output vector every fidelity's ``out`` Function returns, in order
OUTPUTS = ("h1", "h2", "h", "p", "F", "q", "q_in", "q_out", "lam", "V", "m", "det", "det_p")
# det: determinant of d(G, F)/d(h1, h2) (free: dG/dh1). It vanishes where the gas-plus-membrane
#   stiffness along the constant-load path does: a snap-through under mass control.
# det_p: determinant of d(p, F)/d(h1, h2) (free: dp/dh1). It vanishes at the limit point under
#   pressure control (the pressure peak along the load path), where the paper's system (13)-(14),
#   read with dp/dt given, is singular. Mass control passes it stably; the log marks it.
MODE_REST = 0.0  # platform resting on the rig, membrane flat under it
MODE_MOVING = 1.0  # membrane carries the platform (contact) or, for the platform model, airborne


def _u():
    return ca.SX.sym("u", 3)


def cap_law(h1, h2, P) -> tuple:
    """The spherical cap's law at chart (h1, h2) (m, docs/concepts/model.md §1, §3): gauge pressure p (Pa), gas
    volume V (m^3), mean stretch lam (-) and contact radius squared a2 (m^2)."""
    g = ph.geometry(h1, h2, P)
    return ph.pressure(h1, h2, P), g["V"], g["lam"], g["a2"]


def shape_jacobian(h1, h2, P, law=cap_law):
    """G, F and the Jacobian d(G, F)/d(h1, h2) at (possibly composite) expressions h1, h2.

    Differentiates with fresh symbols and substitutes, so h1 and h2 may be expressions of the state.
    ``law(h1, h2, P) -> (p, V, lam, a2)`` is the membrane law (the cap's by default).
    """
    s1, s2 = ca.SX.sym("s1"), ca.SX.sym("s2")
    s = ca.vertcat(s1, s2)
    ps, Vs, _, a2s = law(s1, s2, P)
    Gs = (ps + P["p_env"]) * Vs
    Fs = ca.pi * a2s * ps
    e = ca.vertcat(Gs, Fs)
    G, F, J = ca.substitute([Gs, Fs, ca.jacobian(e, s)], [s], [ca.vertcat(h1, h2)])
    return G, F, J


def pressure_det(h1, h2, P, free: bool = False, law=cap_law):
    """det d(p, F)/d(h1, h2) at (h1, h2), or dp/dh1 along free inflation: the pressure-control fold."""
    s1, s2 = ca.SX.sym("s1"), ca.SX.sym("s2")
    s = ca.vertcat(s1, s2)
    ps, _, _, a2s = law(s1, s2, P)
    Fs = ca.pi * a2s * ps
    J = ca.jacobian(ca.vertcat(ps, Fs), s)
    d = J[0, 0] if free else J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    return ca.substitute(d, s, ca.vertcat(h1, h2))


def fixed_step(f, x, dt: float, substeps: int = 1, method: str = "rk4"):
    """x after ``dt`` s of x' = f(x) (inputs held) by ``substeps`` fixed steps of ``method``, 'euler' or
    'rk4' (casadi expressions or numbers)."""
    h = dt / substeps
    for _ in range(substeps):
        if method == "euler":
            x = x + h * f(x)
            continue
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


class Fidelity:
    """Base class of a plant model. Subclasses override only what differs.

    Attributes
    ----------
    name : str
    state_names : tuple of str, the state vector layout (SI units)
    needs_platform : bool, the scene must have a load (> 0) for this fidelity to make sense
    """

    name = ""
    state_names: tuple = ()
    needs_platform = False

    def __init__(self, material: Material, compressor_csv: str):
        self.space = ph.ParamSpace.for_material(material)
        self.table = ph.compressor_interpolant(str(compressor_csv))

    # --- casadi building blocks -------------------------------------------------------------
    @property
    def nx(self) -> int:
        return len(self.state_names)

    def _sym(self):
        x = ca.SX.sym("x", self.nx)
        u = _u()
        theta, P = self.space.symbols()
        mode = ca.SX.sym("mode")
        return x, u, theta, P, mode

    def contact_law(self, h1, h2, P) -> tuple:
        """The membrane law at chart (h1, h2) (m): p (Pa), V (m^3), lam (-), a2 (m^2); the cap's here."""
        return cap_law(h1, h2, P)

    def flat_h1(self, p, P):
        """Virtual cap height h1 (m) of the flat membrane (h2 = h1) at gauge pressure p (Pa): the chart
        point a resting membrane leaves from."""
        return ph.flat_h1_from_pressure(p, P)

    def _outputs(self, h1, h2, p, q_all, P, det, det_p):
        _, V, lam, a2 = self.contact_law(h1, h2, P)
        F = ca.pi * a2 * p
        q, q_in, q_out = q_all
        m = (p + P["p_env"]) * V / (P["R"] * P["T"])
        return ca.vertcat(h1, h2, h1 - h2, p, F, q, q_in, q_out, lam, V, m, det, det_p)

    @cached_property
    def f(self) -> ca.Function:
        """xdot = f(x, u, theta, mode): the continuous dynamics (SI)."""
        x, u, theta, P, mode = self._sym()
        return ca.Function(f"f_{self.name}", [x, u, theta, mode], [self._rhs(x, u, P, mode)],
                           ["x", "u", "theta", "mode"], ["xdot"])

    @cached_property
    def out(self) -> ca.Function:
        """y = out(x, u, theta, mode), y laid out as :data:`OUTPUTS`."""
        x, u, theta, P, mode = self._sym()
        return ca.Function(f"out_{self.name}", [x, u, theta, mode], [self._out(x, u, P, mode)],
                           ["x", "u", "theta", "mode"], ["y"])

    @cached_property
    def project(self) -> ca.Function:
        """x+ = project(x, theta, mode): Newton steps back onto the algebraic constraints."""
        x, u, theta, P, mode = self._sym()
        return ca.Function(f"proj_{self.name}", [x, theta, mode], [self._project(x, P, mode)],
                           ["x", "theta", "mode"], ["x_proj"])

    def step_function(self, integrator: str, dt: float) -> ca.Function:
        """One fixed step (x, u, theta, mode) -> (x+, mass_in increment, y(x+)), projected.

        ``integrator`` is 'euler' or 'rk4'; the gas-mass quadrature uses the same weights as the
        state, so mass conservation is checked against the scheme's own flow integral. Fusing
        the stages, the projection and the outputs into one Function makes a batched step a single
        call (cached per integrator and dt).
        """
        key = ("step", integrator, float(dt))
        cache = self.__dict__.setdefault("_step_cache", {})
        if key in cache:
            return cache[key]
        if integrator not in ("euler", "rk4"):
            raise ValueError(f"integrator '{integrator}': fixed-step ones are euler, rk4")
        x, u, theta, P, mode = self._sym()
        qi, n = OUTPUTS.index("q"), self.nx

        def fq(z):  # the state's rate and the inflow, integrated together from a gas mass let in of 0
            return ca.vertcat(self._rhs(z[:n], u, P, mode), self._out(z[:n], u, P, mode)[qi])

        z = fixed_step(fq, ca.vertcat(x, 0), dt, 1, integrator)
        xn, dm = z[:n], z[n]
        xp = self._project(xn, P, mode)
        fun = ca.Function(f"step_{self.name}_{integrator}", [x, u, theta, mode],
                          [xp, dm, self._out(xp, u, P, mode)], ["x", "u", "theta", "mode"],
                          ["x_next", "mass_in", "y"])
        cache[key] = fun
        return fun

    def mapped(self, fun: ca.Function, n: int) -> ca.Function:
        """A batched version of a Function over n columns (cached)."""
        # keyed by the Function object itself (kept alive in the cache, so its id is never reused):
        # two step Functions of different dt share a name
        key = (id(fun), n)
        cache = self.__dict__.setdefault("_map_cache", {})
        if key not in cache:
            cache[key] = (fun, fun.map(n))
        return cache[key][1]

    def rhs(self, x, u, P: dict, mode):
        """The continuous dynamics as an expression of x, u, the parameters P (a dict of symbols or
        floats, e.g. with estimated factors applied) and the mode."""
        return self._rhs(x, u, P, mode)

    # --- to override -------------------------------------------------------------------------
    def _rhs(self, x, u, P, mode):
        raise NotImplementedError

    def _out(self, x, u, P, mode):
        raise NotImplementedError

    def _project(self, x, P, mode):
        return x

    def initial_state(self, theta: np.ndarray) -> tuple[np.ndarray, float]:
        """Unpressurised actuator at rest: (x0, mode0); here a loaded one, the platform resting and the
        gas mass (kg) that fills the dead volume at ambient pressure, the other states 0."""
        idx = {n: i for i, n in enumerate(self.space.names)}
        x0 = np.zeros(self.nx)
        x0[0] = theta[idx["p_env"]] * theta[idx["V0"]] / (theta[idx["R"]] * theta[idx["T"]])
        return x0, MODE_REST


class FreeInflation(Fidelity):
    """No load: x = [h1]. h1' = q R T / (dG/dh1) with G = (p + p_env) V along h2 = 0."""

    name = "free"
    state_names = ("h1",)

    def _rhs(self, x, u, P, mode):
        h1 = x[0]
        p = ph.pressure(h1, 0, P)
        q, _, _ = ph.net_flow(u, p, P, self.table)
        _, _, J = shape_jacobian(h1, 0, P)
        return ca.vertcat(q * P["R"] * P["T"] / J[0, 0])

    def _out(self, x, u, P, mode):
        h1 = x[0]
        p = ph.pressure(h1, 0, P)
        _, _, J = shape_jacobian(h1, 0, P)
        return self._outputs(h1, 0 * h1, p, ph.net_flow(u, p, P, self.table), P, J[0, 0],
                             pressure_det(h1, 0, P, free=True))

    def initial_state(self, theta):
        return np.array([0.0]), MODE_MOVING


class QuasiStatic(Fidelity):
    """Dead load, quasi-static platform (the paper's model): x = [m, h1, h2].

    Resting (mode 0): the platform sits on the rig, the membrane is flat, V = V0, p = m R T / V0 -
    p_env; (h1 = h2) is the flat membrane's virtual cap, from
    :func:`~hbma_ctrl.core.physics.flat_h1_from_pressure`.
    Contact (mode 1): F(h1, h2) = W and G(h1, h2) = m R T; (h1, h2) move by the index-reduced
    system ``[G_h1 G_h2; F_h1 F_h2] [h1'; h2'] = [q R T; 0]`` (the paper's eqs. 13-15, with the gas
    written through G so that no pressure derivative is needed). Its determinant ``det`` vanishes at
    a snap-through; the simulator then jumps to the far branch at constant gas mass.
    """

    name = "quasi_static"
    state_names = ("m", "h1", "h2")
    needs_platform = True

    def _pressure(self, x, P, mode):
        m, h1, h2 = x[0], x[1], x[2]
        p_rest = m * P["R"] * P["T"] / P["V0"] - P["p_env"]
        return ca.if_else(mode < 0.5, p_rest, self.contact_law(h1, h2, P)[0])

    def _jac(self, h1, h2, P):
        return shape_jacobian(h1, h2, P, self.contact_law)

    def _rhs(self, x, u, P, mode):
        h1, h2 = x[1], x[2]
        p = self._pressure(x, P, mode)
        q, _, _ = ph.net_flow(u, p, P, self.table)
        _, _, J = self._jac(h1, h2, P)
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        rt = P["R"] * P["T"]
        # Cramer's rule for [J] [h1'; h2'] = [q R T; 0]
        dh1 = q * rt * J[1, 1] / det
        dh2 = -q * rt * J[1, 0] / det
        moving = mode > 0.5
        return ca.vertcat(q, ca.if_else(moving, dh1, 0), ca.if_else(moving, dh2, 0))

    def _out(self, x, u, P, mode):
        m, h1, h2 = x[0], x[1], x[2]
        p = self._pressure(x, P, mode)
        _, _, J = self._jac(h1, h2, P)
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        y = self._outputs(h1, h2, p, ph.net_flow(u, p, P, self.table), P, det,
                          pressure_det(h1, h2, P, law=self.contact_law))
        # resting: the membrane is flat under the plate, V = V0 and the plate carries pi r1^2 p
        rest = mode < 0.5
        y[2] = ca.if_else(rest, 0, y[2])
        y[4] = ca.if_else(rest, ca.pi * P["r1"] ** 2 * p, y[4])
        y[9] = ca.if_else(rest, P["V0"], y[9])
        y[10] = m
        return y

    def _project(self, x, P, mode, iters: int = 2):
        m, h1, h2 = x[0], x[1], x[2]
        rt = P["R"] * P["T"]
        for _ in range(iters):
            G, F, J = self._jac(h1, h2, P)
            r = ca.vertcat(G - m * rt, F - P["W"])
            d = ca.solve(J, r)
            h1, h2 = h1 - d[0], h2 - d[1]
        # resting: the flat membrane's virtual cap follows the gas mass directly
        h_flat = self.flat_h1(m * rt / P["V0"] - P["p_env"], P)
        rest = mode < 0.5
        return ca.vertcat(m, ca.if_else(rest, h_flat, h1), ca.if_else(rest, h_flat, h2))


class DynamicPlatform(Fidelity):
    """Platform with mass and damping: x = [m, h1, z, v] (h1 algebraic, carried).

    Resting (mode 0): as in :class:`QuasiStatic`. Moving (mode 1): z is the platform height above
    its rest, v its velocity; the membrane touches the platform when its free cap would pass z
    (h2 = h1 - z >= 0), otherwise the platform is airborne and F = 0. The membrane is massless
    (quasi-static) and the gas law G(h1, max(h1 - z, 0)) = m R T fixes h1; its index-reduced
    derivative is h1' = (q R T + G_h2 v) / (G_h1 + G_h2) in contact, q R T / G_h1 airborne.
    m_L z'' = F - m_L g - c z'. Touch-down on the rig stop is inelastic (the simulator).
    """

    name = "platform"
    state_names = ("m", "h1", "z", "v")
    needs_platform = True

    def _parts(self, x, P, mode):
        m, h1, z, v = x[0], x[1], x[2], x[3]
        contact = h1 > z
        h2 = ca.if_else(contact, h1 - z, 0)
        p_rest = m * P["R"] * P["T"] / P["V0"] - P["p_env"]
        rest = mode < 0.5
        p = ca.if_else(rest, p_rest, self.contact_law(h1, h2, P)[0])
        return m, h1, z, v, h2, p, contact, rest

    def _rhs(self, x, u, P, mode):
        m, h1, z, v, h2, p, contact, rest = self._parts(x, P, mode)
        q, _, _ = ph.net_flow(u, p, P, self.table)
        rt = P["R"] * P["T"]
        _, _, J = shape_jacobian(h1, h2, P, self.contact_law)
        G_h1, G_h2 = J[0, 0], J[0, 1]
        F = ca.if_else(contact, ca.pi * self.contact_law(h1, h2, P)[3] * p, 0)
        dh1 = ca.if_else(contact, (q * rt + G_h2 * v) / (G_h1 + G_h2), q * rt / G_h1)
        dv = (F - P["W"] - P["c"] * v) / P["M"]
        return ca.vertcat(q, ca.if_else(rest, 0, dh1), ca.if_else(rest, 0, v), ca.if_else(rest, 0, dv))

    def _out(self, x, u, P, mode):
        m, h1, z, v, h2, p, contact, rest = self._parts(x, P, mode)
        # quasi-static snap indicator: det of d(G, F)/d(h1, h2), as in QuasiStatic
        law = self.contact_law
        _, _, J = shape_jacobian(h1, h2, P, law)
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        det_p = ca.if_else(contact, pressure_det(h1, h2, P, law=law), pressure_det(h1, h2, P, free=True, law=law))
        y = self._outputs(h1, h2, p, ph.net_flow(u, p, P, self.table), P, det, det_p)
        y[2] = ca.if_else(rest, 0, z)  # platform height
        y[4] = ca.if_else(rest, ca.pi * P["r1"] ** 2 * p, ca.if_else(contact, y[4], 0))
        y[9] = ca.if_else(rest, P["V0"], y[9])
        y[10] = m
        return y

    def _project(self, x, P, mode, iters: int = 2):
        m, h1, z, v = x[0], x[1], x[2], x[3]
        rt = P["R"] * P["T"]
        for _ in range(iters):
            contact = h1 > z
            h2 = ca.if_else(contact, h1 - z, 0)
            G, _, J = shape_jacobian(h1, h2, P, self.contact_law)
            slope = ca.if_else(contact, J[0, 0] + J[0, 1], J[0, 0])
            h1 = h1 - (G - m * rt) / slope
        h_flat = self.flat_h1(m * rt / P["V0"] - P["p_env"], P)
        rest = mode < 0.5
        return ca.vertcat(m, ca.if_else(rest, h_flat, h1), ca.if_else(rest, 0, z), ca.if_else(rest, 0, v))


FIDELITIES: dict[str, type[Fidelity]] = {c.name: c for c in (FreeInflation, QuasiStatic, DynamicPlatform)}


def make_fidelity(name: str, material: Material, compressor_csv: str) -> Fidelity:
    """Build a fidelity by name ('free', 'quasi_static', 'platform'); typos get the closest name."""
    if name not in FIDELITIES:
        hint = did_you_mean(name, FIDELITIES)
        raise ValueError(f"fidelity: unknown '{name}'{hint}; allowed: {', '.join(FIDELITIES)}")
    # the Functions depend on the material family and the theta layout (ParamSpace), not on the
    # parameter values, which are inputs: one build serves every actuator of that family
    key = (name, ph.ParamSpace.for_material(material), str(compressor_csv))
    if key not in _FID_CACHE:
        _FID_CACHE[key] = FIDELITIES[name](material, str(compressor_csv))
    return _FID_CACHE[key]


_FID_CACHE: dict = {}
