"""The simulated rig: the "truth" that estimators and controllers are tested against (SI).

A :class:`Rig` is the plant simulator at a *higher fidelity* than the estimators' and controllers'
model, with *mismatched* parameters and a realistic sensor, so that nothing is ever tested against
its own model:

- fidelity ``platform`` (platform with mass and damping, ``m_L z'' = F - m_L g - c z'``) while a
  load is on; the estimators use the quasi-static (dead-load) model. With no load the membrane
  inflates freely (fidelity ``free``); a load put on mid-run (:meth:`Rig.set_load`) lands on the
  membrane at its current apex height, taking it off lets the membrane inflate freely again;
- parameters off nominal: every modulus of the material times ``modulus_scale`` (default 1.15),
  compressor flow times ``flow_scale`` (0.9), dead volume times ``V0_scale`` (1.2), the outlet's
  conductance times ``C_out_scale`` (1);
- the membrane's law: the exact axisymmetric membrane (``membrane = "exact"``, the default), or the
  spherical cap (``"cap"``, the law of the cap models, ``hbma_ctrl.models.defaults.CAP_CHAMBER``);
- structural mismatches (docs/concepts/truth.md), on by default (:data:`STRUCTURED_RIG`; :data:`CAP_RIG` turns
  them off with the cap): the valves switch ``valve_delay`` (5 ms) after their command and cannot
  open for less than ``valve_min_on`` (2 ms) of each PWM period (one sample period): a shorter duty
  is dropped or lengthened to the minimum; the pump's map has another *shape*, its flow tilted with
  back pressure by ``compressor_tilt`` (0.2: +10 % at 0 Pa, -10 % at the map's top pressure, the
  same mean); the sensor lags the pressure by a first-order lag of ``sensor_tau`` (3 ms, a
  piezoresistive sensor behind a short tube);
- the pressure sensor: additive Gaussian noise (``noise_std``, 200 Pa), saturation at
  ``sensor_range`` (35 kPa: a reading never exceeds it), dropouts (NaN) with probability
  ``dropout_prob``, sampled every ``sample_period`` (10 ms); the command is held between samples
  (zero-order hold).

The random stream is a :class:`numpy.random.Generator` seeded by ``seed``: a rig is deterministic.
:func:`simulate_rig` runs a batch of open-loop trials (each its own schedule) through one batched
plant, which the estimator benchmarks and the protocol scenario use.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import hashlib
from pathlib import Path

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import cache_dir
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics, check_range
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.core.physics import load_compressor_table
from hbma_ctrl.models.fidelity import MODE_MOVING, MODE_REST, OUTPUTS, make_fidelity
from hbma_ctrl.models.fidelity_exact import make_exact_free, make_exact_loaded
from hbma_ctrl.models.shape import ShapeSolver
from hbma_ctrl.sim.simulate import Plant, period_plant
from hbma_ctrl.sim.trial import Trial

__all__ = ["RigSettings", "Rig", "RigRecord", "ValveLine", "mismatched", "scaled", "simulate_rig", "tilted_map",
           "TRUTH_KEYS", "IDEAL_STRUCTURE", "STRUCTURED_RIG", "CAP_RIG"]

#: RigSettings keywords that switch the structural mismatches off (a rig with the model's structure:
#: for tests of parameter identification, which need the fitted model's form to be the rig's)
IDEAL_STRUCTURE = {"valve_delay": 0.0, "valve_min_on": 0.0, "compressor_tilt": 0.0, "sensor_tau": 0.0}
#: the structurally different truth, RigSettings' defaults: the exact membrane, 5 ms valve delay,
#: 2 ms minimum opening, a pump map tilted with back pressure, a 3 ms sensor lag
STRUCTURED_RIG = {"membrane": "exact", "valve_delay": 0.005, "valve_min_on": 0.002, "compressor_tilt": 0.2,
                  "sensor_tau": 0.003}
#: the cap rig: the cap models' own law with scalar mismatches only, a truth of the models' own
#: structure (docs/concepts/truth.md, "The simple rig"; its models are ``hbma_ctrl.models.defaults.CAP_CHAMBER``)
CAP_RIG = {"membrane": "cap", **IDEAL_STRUCTURE}

#: keys of :meth:`Rig.truth`
TRUTH_KEYS = ("t", "h1", "h2", "h", "p", "F", "m")
_RIG_FIDELITIES = ("platform", "quasi_static")
_RIG_MEMBRANES = ("exact", "cap")


@dataclass
class RigSettings(Settings):
    """How the simulated rig differs from the nominal model, and its sensor (SI; each field's unit,
    range and one-line doc are in its declaration).

    fidelity 'quasi_static' (a dead load) is only to check an estimator against its own model
    structure. membrane 'exact' is the exact axisymmetric membrane's tables (free inflation
    :func:`hbma_ctrl.models.fidelity_exact.make_exact_free`, and with a load on the exact flat-plate
    contact, :func:`hbma_ctrl.models.fidelity_exact.make_exact_loaded`); 'cap' the spherical cap, the
    cap models' own law (see :data:`CAP_RIG`). The integrator is fixed-step (:mod:`hbma_ctrl.sim.simulate`).
    valve_delay is rounded to the internal step; the pump speed is not delayed. A duty d with d T
    (T the sample period, the PWM period) below half of valve_min_on is dropped (valve shut), below it
    lengthened to it (to the whole period when it is longer than T). compressor_tilt k: the pump's
    flow at back pressure p is the map's times (1 - k (p / p_top - 1/2)), p_top the map's top pressure.

    The defaults are :data:`STRUCTURED_RIG`: a truth that differs from the models in structure, not
    only in constants. :data:`CAP_RIG` gives the cap rig (the cap models' own law, scalar mismatches only).
    """

    WHERE = "rig"

    fidelity: str = setting("platform", choices=_RIG_FIDELITIES, doc="plant model while a load is on")
    modulus_scale: float = setting(1.15, lo=0.2, hi=5.0, doc="every modulus of the material times this")
    flow_scale: float = setting(0.9, lo=0.0, hi=5.0, doc="compressor map times this (on top of the pneumatics' own)")
    V0_scale: float = setting(1.2, lo=0.2, hi=5.0, doc="dead volume times this")
    C_out_scale: float = setting(1.0, lo=0.05, hi=20.0, doc="the outlet valve's sonic conductance times this")
    noise_std: float = setting(200.0, lo=0.0, hi=1e4, unit="Pa", user="kPa", doc="sensor noise, one sigma")
    sensor_range: float = setting(35e3, lo=1e3, hi=1e6, unit="Pa", user="kPa", doc="sensor saturation pressure")
    sample_period: float = setting(0.01, lo=0.0, hi=1.0, lo_open=True, unit="s", user="ms",
                                   doc="sensor and command period")
    dropout_prob: float = setting(0.0, lo=0.0, hi=1.0, doc="probability that a sample is missing")
    seed: int = setting(0, integer=True, lo=0, doc="seed of the noise and dropout stream")
    integrator: str = setting("rk4", choices=("rk4", "euler"), doc="fixed-step scheme")
    dt: float | None = setting(None, lo=1e-7, hi=1.0, lo_open=True, unit="s", user="ms",
                               doc="internal step, at most sample_period_ms; default per fidelity")
    # defaults: STRUCTURED_RIG, a truth of another structure than the estimators' and controllers'
    # models (valve timing, pump shape, sensor lag); CAP_RIG is a truth of the cap models' own structure
    membrane: str = setting(STRUCTURED_RIG["membrane"], choices=_RIG_MEMBRANES,
                            doc="membrane law, free and on the plate: exact (exact membrane tables) or cap (spherical cap)")
    valve_delay: float = setting(STRUCTURED_RIG["valve_delay"], lo=0.0, hi=0.1, unit="s", user="ms",
                                 doc="the valves act this long after their command (a small solenoid)")
    valve_min_on: float = setting(STRUCTURED_RIG["valve_min_on"], lo=0.0, hi=0.1, unit="s", user="ms",
                                  doc="shortest valve opening per PWM (sample) period (a small solenoid)")
    compressor_tilt: float = setting(STRUCTURED_RIG["compressor_tilt"], lo=-1.0, hi=1.0,
                                     doc="pump flow times 1 - k (p / p_top - 1/2): another shape (0 = the map's own)")
    sensor_tau: float = setting(STRUCTURED_RIG["sensor_tau"], lo=0.0, hi=1.0, unit="s", user="ms",
                                doc="first-order lag of the pressure sensor (0 = none)")

    def check_rules(self) -> None:
        if self.dt is not None:
            self.within("dt", hi=self.sample_period)

    def valve_duty(self, d):
        """A valve's duty d (0-1; an array or a casadi expression) as the valve realises it with its
        minimum on-time within one PWM period."""
        if self.valve_min_on <= 0:
            return d
        frac = min(1.0, self.valve_min_on / self.sample_period)
        return ca.if_else(d < 0.5 * frac, 0.0, ca.fmax(d, frac))

    def shape_command(self, u: np.ndarray) -> np.ndarray:
        """Duties the valves can realise (:meth:`valve_duty`); rows speed, inlet, outlet (3 or 3 x n),
        each 0-1."""
        u = np.array(u, dtype=float)
        for i in (1, 2):
            u[i] = np.asarray(self.valve_duty(u[i]), dtype=float).reshape(u[i].shape)
        return u

    def sense(self, y_prev, p_prev, p_now):
        """One sample of the sensor's first-order lag (Pa; arrays and casadi expressions work): the exact
        response of y' = (p - y) / sensor_tau over one sample period to a pressure moving linearly from
        p_prev to p_now (a ramp is read sensor_tau late, as by the continuous sensor)."""
        if self.sensor_tau <= 0:
            return p_now
        r = self.sample_period / self.sensor_tau
        a = np.exp(-r)
        return a * y_prev + (1 - a) * p_prev + (p_now - p_prev) * (1 - (1 - a) / r)

    def plant_fidelity(self, loaded: bool, material, csv: str):
        """The rig's plant model: with a load on ``fidelity`` (the exact contact or the cap's, by
        ``membrane``), else free inflation of the exact membrane or the cap."""
        if self.membrane == "exact":
            return make_exact_loaded(self.fidelity, material, csv) if loaded else make_exact_free(material, csv)
        return make_fidelity(self.fidelity if loaded else "free", material, csv)


def mismatched(actuator: Actuator, pneumatics: Pneumatics, settings: RigSettings
               ) -> tuple[Actuator, Pneumatics]:
    """The rig's (true) actuator and pneumatics: nominal ones with the settings' mismatch applied."""
    act, pn = scaled(actuator, pneumatics, settings.flow_scale, settings.modulus_scale, settings.V0_scale)
    if settings.C_out_scale != 1.0:
        pn = replace(pn, outlet=replace(pn.outlet, C=pn.outlet.C * settings.C_out_scale))
    if settings.compressor_tilt != 0:
        pn = replace(pn, compressor_csv=str(tilted_map(pneumatics.csv_path, settings.compressor_tilt)))
    return act, pn


def scaled(actuator: Actuator, pneumatics: Pneumatics, b: float, k: float, c: float) -> tuple[Actuator, Pneumatics]:
    """The actuator and pneumatics with pump flow x b, every modulus x k and dead volume x c."""
    return (replace(actuator, material=actuator.material.scaled(k), V0=actuator.V0 * c),
            replace(pneumatics, flow_scale=pneumatics.flow_scale * b))


def tilted_map(csv_path: Path | str, tilt: float) -> Path:
    """A compressor map of another shape: flow times (1 - tilt (p / p_top - 1/2)), never below 0.

    Written once (keyed by the source map's bytes and the tilt) under ``$HBMA_CTRL_CACHE/rig``, so
    the plant's map is an ordinary CSV and its interpolant is built like the nominal one.
    """
    src = Path(csv_path)
    key = hashlib.sha256(src.read_bytes() + repr(float(tilt)).encode()).hexdigest()[:16]
    out = cache_dir() / "rig" / f"compressor_tilt_{key}.csv"
    if out.exists():
        return out
    s, p, grid = load_compressor_table(src)
    factor = np.maximum(0.0, 1.0 - tilt * (p / p.max() - 0.5))
    lines = [f"# {src.name} with its flow tilted by {tilt:g} over pressure (hbma_ctrl.sim.rig.tilted_map)",
             "speed,pressure_pa,mass_flow_kgs"]
    lines += [f"{float(si)!r},{float(pj)!r},{float(grid[i, j] * factor[j])!r}" for i, si in enumerate(s) for j, pj in enumerate(p)]
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(f".{np.random.default_rng().integers(1 << 30)}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(out)
    return out


class ValveLine:
    """Commands as the valves see them: shaped (minimum on-time) and delayed by ``valve_delay``."""

    def __init__(self, s: RigSettings, n: int = 1):
        self.s = s
        self.hist: list = []  # (time sent, shaped command 3 x n), oldest first
        self.n = n

    def send(self, t: float, u: np.ndarray) -> None:
        self.hist.append((t, self.s.shape_command(np.asarray(u, dtype=float).reshape(3, self.n))))
        keep = int(np.ceil(self.s.valve_delay / self.s.sample_period)) + 2
        del self.hist[:-keep]

    def at(self, tau: float) -> np.ndarray:
        """Inputs (3 x n) acting at time tau: the speed sent last, the valves as sent at tau - delay."""
        speed = self.hist[-1][1][0]
        valves = np.zeros((2, self.n))  # before any command reaches them the valves are shut
        for t_sent, u in self.hist:
            if t_sent <= tau - self.s.valve_delay + 1e-12:
                valves = u[1:]
        return np.vstack([speed[None, :], valves])

    def drive(self, plant: Plant, t: float, through=None) -> None:
        """Advance ``plant`` over the sample period from t (s) in its internal steps, each with the
        inputs acting then (mapped by ``through`` first when given: a shared pump's manifold)."""
        for j in range(max(1, int(round(self.s.sample_period / plant.dt)))):
            u = self.at(t + j * plant.dt)
            plant.advance(u if through is None else through(u), plant.dt)


class Rig:
    """One simulated chamber with its pressure sensor (see module docstring). SI throughout.

    ``apply(command)`` holds the command for one sample period and advances the plant;
    ``measure()`` returns the sensor reading at the current time (Pa; never above the sensor range;
    NaN on a dropout); ``truth()`` the true state; ``set_load(mass_kg)`` changes the load now.
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, platform: Platform,
                 settings: RigSettings | None = None):
        self.settings = (settings or RigSettings()).validate()
        actuator.validate()
        pneumatics.validate()
        platform.validate()
        self.actuator, self.pneumatics = mismatched(actuator, pneumatics, self.settings)
        self.platform = platform
        self._rng = np.random.default_rng(self.settings.seed)
        self._csv = str(self.pneumatics.csv_path)
        self._free, self._loaded = (self.settings.plant_fidelity(loaded, self.actuator.material, self._csv)
                                    for loaded in (False, True))
        self._u = np.zeros(3)
        self.t = 0.0
        self.events: list = []
        self._plant = self._new_plant(platform)
        self._t_plant0 = 0.0  # rig time at which the current plant's clock started
        self._valves = ValveLine(self.settings)
        self._p_sensed = self._p_prev = float(self._plant.output("p")[0])  # lagged sensor state, true p, Pa

    # --- plant bookkeeping ------------------------------------------------------------------
    def _theta(self, fid, platform: Platform) -> np.ndarray:
        return fid.space.values(self.actuator, self.pneumatics, platform)

    def _new_plant(self, platform: Platform) -> Plant:
        fid = self._free if platform.mass <= 0 else self._loaded
        s = self.settings
        return period_plant(fid, self._theta(fid, platform)[:, None], s.integrator, s.sample_period, s.dt)

    @property
    def fidelity(self) -> str:
        """Name of the plant model in use now ('free' while no load is on)."""
        return self._plant.fid.name

    def apply(self, command: Command) -> None:
        """Hold ``command`` for one sample period and advance the plant."""
        u = command.as_array() if isinstance(command, Command) else np.asarray(command, dtype=float)
        self._u = u
        n0 = len(self._plant.events[0])
        plant = self._plant
        self._valves.send(self.t, u)
        self._valves.drive(plant, self.t)
        self.events += [(self._t_plant0 + e[0], e[1]) for e in self._plant.events[0][n0:]]
        self.t += self.settings.sample_period
        p_now = float(plant.output("p")[0])
        self._p_sensed = self.settings.sense(self._p_sensed, self._p_prev, p_now)
        self._p_prev = p_now
        if not self._plant.alive[0]:
            raise RuntimeError(f"rig: the plant diverged at t = {self.t:.3f} s")

    def measure(self) -> float:
        """Sensor reading now, Pa: lagged true pressure + noise, saturated at the range; NaN on dropout."""
        s = self.settings
        noise = self._rng.standard_normal() * s.noise_std
        drop = self._rng.random() < s.dropout_prob if s.dropout_prob > 0 else False
        if drop:
            return float("nan")
        return float(min(self._p_sensed + noise, s.sensor_range))

    def truth(self) -> dict:
        """True h1, h2, h (m), p (Pa), F (N), m (gas mass, kg) and t (s) now."""
        y = self._plant.y[:, 0]
        out = {k: float(y[OUTPUTS.index(k)]) for k in ("h1", "h2", "h", "p", "F", "m")}
        out["t"] = self.t
        return out

    def set_load(self, mass_kg: float) -> None:
        """Put a load of ``mass_kg`` (plus the platform's own mass) on now; 0 takes it off."""
        check_range("rig.set_load", "mass_kg", mass_kg, 0.0, 50.0, "kg")
        new = replace(self.platform, load=float(mass_kg))
        old_plant = self._plant
        was_free = old_plant.fid.name == "free"
        now_free = new.mass <= 0
        tr = self.truth()
        if was_free and now_free:
            self.platform = new
            return
        if not was_free and not now_free:
            th = self._theta(self._loaded, new)
            old_plant.thetas[:, 0] = th  # the batch shares this array
            self.platform = new
            self.events.append((self.t, f"load_set_{mass_kg:.3f}kg"))
            return
        self.platform = new
        plant = self._new_plant(new)
        fid = plant.fid
        if now_free:
            # the load leaves: the membrane re-inflates freely at constant gas mass
            x = np.array([self._free_h1(tr["m"])])
            mode = MODE_MOVING
        else:
            # the load is placed on the apex: platform at the membrane's height, at rest
            if fid.name == "platform":
                x = np.array([tr["m"], tr["h1"], tr["h"], 0.0])
            else:
                x = np.array([tr["m"], tr["h1"], 0.0])
            mode = MODE_MOVING if tr["h"] > 1e-6 else MODE_REST
            x = np.asarray(fid.project(x, plant.thetas[:, 0], mode)).ravel()
        plant.X = x[:, None].copy()
        plant.mode = np.array([mode])
        plant.set_inputs(self._u[:, None])
        plant.y = plant.batch.y(plant.X, plant.U, plant.mode)
        self._plant = plant
        self._t_plant0 = self.t
        self.events.append((self.t, f"load_set_{mass_kg:.3f}kg"))

    def _free_h1(self, m: float) -> float:
        """Free-inflation apex height (m) holding gas mass m (kg), from the current one."""
        fid = self._free
        if getattr(fid, "membrane", "cap") == "exact":
            return _exact_free_h(fid, fid.space.values(self.actuator, self.pneumatics, Platform()), m)
        solver = ShapeSolver(fid.space, fid.space.values(self.actuator, self.pneumatics, Platform()))
        return solver.free_h1(m * (self.actuator.R * self.actuator.T), self.truth()["h1"])


def _exact_free_h(fid, theta: np.ndarray, m: float) -> float:
    """Apex height (m) of the exact free membrane holding gas mass m (kg): bisection on the gas law.

    The gas mass grows with the height (dG/dh >= p_env dV/dh > 0), so the root is unique.
    """
    mi = OUTPUTS.index("m")

    def mass(h: float) -> float:
        return float(fid.out([h], [0.0, 0.0, 0.0], theta, 1.0)[mi])

    r1 = float(theta[fid.space.names.index("r1")])
    lo, hi = 0.0, fid.x_max * r1
    if m <= mass(lo):
        return 0.0
    while mass(hi) < m and hi < 10 * r1:  # past the table the interpolant extrapolates
        hi *= 1.5
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mass(mid) < m else (lo, mid)
    return 0.5 * (lo + hi)


@dataclass
class RigRecord:
    """Sampled rig run of one trial (SI): times, commands (n x 3), readings, truth series."""

    name: str
    t: np.ndarray
    u: np.ndarray
    meas: np.ndarray
    truth: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    status: str = "ok"


def simulate_rig(trials: list[Trial], settings: RigSettings | None = None,
                 stream_ids: list[int] | None = None) -> list[RigRecord]:
    """Run open-loop trials (each with its schedule) on the rig, all at once per fidelity.

    Trials with a load share one batched ``platform`` plant, unloaded ones one ``free`` plant.
    Readings use an independent stream per trial, seeded by (seed, its stream id); the ids default
    to the trials' positions in the list (a caller that splits a list into batches passes the
    positions in the whole list, so a trial's noise does not depend on the batching). Sample k is taken at
    t = k * sample_period, before the command for [t, t + period) is applied; the command is the
    schedule at the middle of the period.
    """
    s = (settings or RigSettings()).validate()
    ids = list(range(len(trials))) if stream_ids is None else [int(i) for i in stream_ids]
    if len(ids) != len(trials):
        raise ValueError(f"simulate_rig: {len(ids)} stream_ids for {len(trials)} trials")
    recs: list = [None] * len(trials)
    groups: dict = {}
    for i, tr in enumerate(trials):
        tr.validate()
        loaded = tr.platform.mass > 0
        key = (loaded, type(tr.actuator.material), str(tr.pneumatics.csv_path))
        groups.setdefault(key, []).append(i)
    for (loaded, _, csvp), idx in groups.items():
        pairs = [mismatched(trials[i].actuator, trials[i].pneumatics, s) for i in idx]
        csvp = str(pairs[0][1].csv_path)  # the rig's own map (another shape when tilted)
        fid = s.plant_fidelity(loaded, pairs[0][0].material, csvp)
        thetas = np.column_stack([fid.space.values(a, p, trials[i].platform)
                                  for (a, p), i in zip(pairs, idx)])
        plant = period_plant(fid, thetas, s.integrator, s.sample_period, s.dt, compile=True)
        T = max(trials[i].duration for i in idx)
        K = int(round(T / s.sample_period)) + 1
        n = len(idx)
        Y = np.zeros((K, len(OUTPUTS), n))
        Ucols = np.zeros((K, 3, n))
        valves = ValveLine(s, n)
        for k in range(K):
            t = k * s.sample_period
            U = np.column_stack([trials[i].schedule.at(t + 0.5 * s.sample_period) for i in idx])
            valves.send(t, U)
            plant.set_inputs(valves.at(t))
            Y[k] = plant.y
            Ucols[k] = U
            if k < K - 1:
                valves.drive(plant, t)
        # the sensor's first-order lag, sampled (the same recursion as Rig.measure)
        ptrue = Y[:, OUTPUTS.index("p"), :]
        sensed = ptrue.copy()
        for k in range(1, K):
            sensed[k] = s.sense(sensed[k - 1], ptrue[k - 1], ptrue[k])
        for j, i in enumerate(idx):
            rng = np.random.default_rng([s.seed, ids[i]])
            Kj = int(round(trials[i].duration / s.sample_period)) + 1
            y = Y[:Kj, :, j]
            p = sensed[:Kj, j]
            meas = np.minimum(p + s.noise_std * rng.standard_normal(Kj), s.sensor_range)
            if s.dropout_prob > 0:
                meas[rng.random(Kj) < s.dropout_prob] = np.nan
            truth = {k: y[:, OUTPUTS.index(k)].copy() for k in ("h1", "h2", "h", "p", "F", "m")}
            tt = np.arange(Kj) * s.sample_period
            truth["t"] = tt
            status = "ok" if plant.alive[j] else "diverged"
            recs[i] = RigRecord(trials[i].name, tt, Ucols[:Kj, :, j].copy(), meas, truth,
                                list(plant.events[j]), status)
    return recs
