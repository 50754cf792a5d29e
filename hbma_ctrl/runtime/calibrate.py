"""Start-up calibration of one chamber before its loop closes: learn the pump-flow, modulus and
dead-volume factors from a short known excitation (SI, no I/O).

Why: the estimator starts from the nominal model and learns the factors from whatever the closed
loop happens to excite. In free inflation the three trade off (a weaker pump, a larger dead volume
and a softer membrane all slow the pressure rise), so on some noise seeds the filter settles on a
modulus 5-10 % low and reports the cap 0.3-0.6 mm higher than it is (the 0 g step to 8 mm then
ends outside its 0.3 mm band on 9 of 20 seeds). A known excitation separates them: the pump pulse
into the closed chamber gives the flow over the chamber's compliance, the vent through the known
outlet the compliance alone (dead volume plus, for a lifted membrane, the cap's, which the modulus
sets) as a function of pressure.

The excitation (:class:`StartupCalibration`, ``tick(t, reading_pa) -> (command, done)``):

1. ``vent``: outlet open until the readings average within ``rest_tol`` of zero (at least
   ``vent_min``, at most ``vent_max``: still pressurised then = the calibration fails, ``status``
   says why);
2. ``pump``: compressor at ``speed``, inlet open, outlet closed, until a reading exceeds
   ``p_stop`` or ``pump_max`` elapsed; a missing reading stops it at once (no pumping blind);
3. ``hold``: everything closed for ``hold`` s (the pressure settles on the chamber's compliance);
4. ``vent``: outlet open for ``vent_end`` s; the loop then starts from (nearly) ambient.

``p_stop`` is checked against every reading, so the pressure never goes more than one sample's rise
above it whatever the membrane's modulus (``p_stop`` must be below ``p_max``). With a load on the
membrane the pulse stops at ``LOADED_STOP`` of the load's lift-off pressure (``W / (pi r1^2)``): the
membrane stays flat, where the model's pressure is the gas law alone and the rig's platform
dynamics (its mass and damping, which the fit's quasi-static model lacks) play no part -- lifted,
they biased the fit (modulus factor 1.10 +- 0.01 for the rig's 1.15 at 400 g). Flat, the modulus is
not observable: its prior comes back unchanged and the estimator learns it in the loop.

The fit: the readings from the pump's start on are compared with the model's pressure (the
simulator's ``free`` fidelity, or ``quasi_static`` with the known load) for the commands sent, and
``(b, k, c)`` minimise the normalised residuals plus the prior (:func:`hbma_ctrl.core.identify.identify`,
bounded to [0.5, 2]; the Jacobian by forward differences, all columns in one batched simulation).
``result`` holds the factors, their covariance (the Gauss-Newton posterior) and the residual RMS.
:func:`hand_to_estimator` writes them into an estimator with the factor states ``b, k, c``
(the EKF, the UKF) as its prior: means replaced, their correlations with the other states cut.

Given an ``estimator`` (one that has not stepped yet), the calibration runs it over the whole
excitation when done: first reading, the fitted factors handed over, every later reading with the
command held before it, the factors handed over again (the filter's own factor learning on the
same data would count it twice). So the filter tracks the gas and the membrane through the
excitation -- a free membrane is not flat again after the final vent, it keeps a ~1 mm cap at a few
tens of Pa for seconds, and a filter started there as flat takes the cap's rise for a phantom
load -- and it dates the lift-off with the calibrated factors (with the nominal ones a free
membrane's lift-off can leave a phantom load of a few hundredths of a newton, 0.4 mm at a 2 mm
cap). The loop then continues with that estimator and the calibration's last command.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hbma_ctrl.estimators.common import FACTOR_RANGE, FilterSettings
from hbma_ctrl.core.identify import identify
from hbma_ctrl.core.interfaces import Command, Estimator, check_role
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.models.actuation import CommandTiming, sensor_delay_setting, valve_delay_setting
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE, DEFAULT_SENSOR_DELAY, DEFAULT_VALVE_DELAY
from hbma_ctrl.models.fidelity import make_fidelity
from hbma_ctrl.models.fidelity_exact import make_exact_free
from hbma_ctrl.models.reduced import MEMBRANES
from hbma_ctrl.sim.rig import scaled
from hbma_ctrl.sim.simulate import period_plant

__all__ = ["CalibrationSettings", "CalibrationResult", "StartupCalibration", "hand_to_estimator",
           "FACTOR_NAMES"]

#: the learnt factors, in the estimator's state names: pump flow, modulus, dead volume
FACTOR_NAMES = ("b", "k", "c")
_BOUNDS = FACTOR_RANGE  # the estimator's own factor range: off by more is a broken rig
_FD_STEP = 0.01
#: with a load on, the pump stops at this fraction of the load's lift-off pressure (stays flat)
LOADED_STOP = 0.8
#: the pump stops when a reading falls this many sensor sigmas below the pulse's peak
LIMIT_FALL_SIGMAS = 5.0
_VENT = Command(0.0, 0.0, 1.0)
_HOLD = Command(0.0, 0.0, 0.0)


@dataclass
class CalibrationSettings(Settings):
    """The excitation and the fit (SI; each field's unit, range and one-line doc are in its declaration).

    rest_tol : the first vent ends when the mean of the last ``rest_samples`` readings is within
        this of zero.
    prior_mean, prior_std : the prior on (b, k, c): its means (1: the nominal chamber; a fit's values)
        and one sigmas (the estimator's initial values and spreads).
    valve_delay, sensor_delay : the fit's model takes the commands as acting that late
        (:mod:`hbma_ctrl.models.actuation`; the estimator's settings, so both see the same chamber).
        Unmodelled, 5 ms of valve delay and 3 ms of sensor lag make the fit's dead volume 20-35 % too large.
    membrane : on an exact membrane the cap fits a modulus about 5 % high. Defaults:
        :mod:`hbma_ctrl.models.defaults`.
    handover_std_floor : the fit's Gauss-Newton sigma assumes the model is the chamber (0.004 for
        the flow factor); on a rig that differs in structure (a pump map of another shape, valves
        with a minimum opening) the factors it fits at the pulse's pressures are off elsewhere, and a
        filter held that tight cannot follow (`bench loop --rig structured`: 400 g passed 7/10 seeds,
        10/10 with 0.08).
    """

    WHERE = "calibration"

    p_max: float = setting(35e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa",
                           doc="the pressure limit the calibration must respect (the controller's)")
    p_stop: float = setting(17e3, lo=0.0, hi=1e6, lo_open=True, hi_open=True, unit="Pa",
                            doc="the pump stops at the first reading above this (below p_max)")
    speed: float = setting(1.0, lo=0.0, hi=1.0, lo_open=True, doc="compressor speed during the pulse")
    pump_max: float = setting(1.0, lo=0.0, hi=5.0, lo_open=True, unit="s", doc="longest pump pulse")
    hold: float = setting(0.1, lo=0.0, hi=5.0, unit="s", doc="all valves closed after the pulse")
    vent_min: float = setting(0.1, lo=0.0, hi=5.0, unit="s", doc="the first vent lasts at least this long")
    vent_max: float = setting(2.0, lo=0.0, hi=30.0, unit="s",
                              doc="the first vent lasts at most this long (at least vent_min)")
    vent_end: float = setting(0.5, lo=0.0, hi=5.0, unit="s", doc="the final vent")
    vent_duty: float = setting(1.0, lo=0.0, hi=1.0, lo_open=True,
                               doc="outlet duty of the final vent (a slower vent samples the low pressures more)")
    rest_tol: float = setting(500.0, lo=0.0, hi=1e5, lo_open=True, unit="Pa",
                              doc="the first vent ends when the readings average within this of zero")
    rest_samples: int = setting(5, integer=True, lo=1, doc="readings averaged for the rest check")
    sample_period: float = setting(0.01, lo=0.0, hi=1.0, lo_open=True, unit="s",
                                   doc="the reading and command period (the rig's)")
    noise_std: float = setting(200.0, lo=0.0, hi=1e4, lo_open=True, unit="Pa",
                               doc="the sensor's one sigma (weights the residuals)")
    sensor_range: float = setting(35e3, lo=1e3, hi=1e6, unit="Pa",
                                  doc="readings at or above this are saturated and not fitted")
    prior_mean: tuple = setting((FilterSettings.flow_factor_init, FilterSettings.modulus_init,
                                 FilterSettings.dead_volume_init), lo=FACTOR_RANGE[0], hi=FACTOR_RANGE[1],
                                parts=FACTOR_NAMES, doc="prior means of the factors (b, k, c)")
    prior_std: tuple = setting((FilterSettings.flow_factor_init_std, FilterSettings.modulus_init_std,
                                FilterSettings.dead_volume_init_std), lo=0.0, hi=10.0, lo_open=True,
                               parts=FACTOR_NAMES, doc="prior one sigmas of the factors (b, k, c)")
    valve_delay: float = valve_delay_setting(DEFAULT_VALVE_DELAY)
    sensor_delay: float = sensor_delay_setting(DEFAULT_SENSOR_DELAY)
    membrane: str = setting(DEFAULT_MEMBRANE, choices=MEMBRANES, doc="the fit's free-inflation law (the estimator's)")
    handover_std_floor: float = setting(0.08, lo=0.0, hi=1.0,
                                        doc="the estimator's prior sigma of each factor is at least this")

    def check_rules(self) -> None:
        self.within("p_stop", hi=self.p_max)
        self.within("vent_max", lo=self.vent_min)


@dataclass(frozen=True)
class CalibrationResult:
    """What the calibration learnt: factors (-), their covariance (3 x 3, order ``FACTOR_NAMES``),
    the RMS of the fit's residuals (Pa), the number of readings fitted and the peak reading (Pa)."""

    b: float
    k: float
    c: float
    cov: np.ndarray
    residual_rms: float
    n_readings: int
    p_peak: float

    @property
    def factors(self) -> np.ndarray:
        """(b, k, c) as an array."""
        return np.array([self.b, self.k, self.c])

    @property
    def std(self) -> np.ndarray:
        """One sigma of (b, k, c)."""
        return np.sqrt(np.diag(self.cov))

    def floored(self, std_floor: float) -> "CalibrationResult":
        """The result with every factor's sigma raised to at least ``std_floor`` (correlations kept)."""
        sd = self.std
        scale = np.maximum(sd, std_floor) / np.where(sd > 0, sd, 1.0)
        cov = self.cov * np.outer(scale, scale)
        if np.any(sd <= 0):
            cov[np.diag_indices(3)] = np.maximum(np.diag(cov), std_floor ** 2)
        return replace(self, cov=cov)


class StartupCalibration:
    """The start-up excitation and fit of one chamber (see module doc).

    ``tick(t, reading_pa) -> (command, done)``: one sample at time t (s) with the pressure reading
    (Pa, NaN = dropout); the command is held until the next tick. When ``done``, ``result`` holds
    the :class:`CalibrationResult` (None if it failed; ``status`` says why) and the command is the
    vent. ``platform`` = the known load during the calibration (None: no load; with a load the
    pulse stops below its lift-off pressure, ``p_stop`` the pressure it stops at). ``estimator``
    (optional, an :class:`~hbma_ctrl.core.interfaces.Estimator`, not yet stepped) is run over the
    excitation when it is done, with the result handed over when its ``state_names`` has the factor
    states (module doc); ``estimate`` is its last output.
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: CalibrationSettings | None = None,
                 platform: Platform | None = None, estimator: Estimator | None = None):
        if estimator is not None:
            check_role(estimator, Estimator, "StartupCalibration: estimator")
        self.settings = (settings or CalibrationSettings()).validate()
        actuator.validate()
        pneumatics.validate()
        self.actuator, self.pneumatics = actuator, pneumatics
        self.platform = platform or Platform(load=0.0)
        self.platform.validate()
        self.p_stop = self.settings.p_stop
        if self.platform.mass > 0:
            p_lift = self.platform.mass * self.platform.g / (np.pi * actuator.r1 ** 2)
            self.p_stop = min(self.p_stop, LOADED_STOP * p_lift)
        self.phase = "vent"
        self.status = "running"
        self.result: CalibrationResult | None = None
        self.command = _VENT
        self.estimator = estimator
        self.estimate = None
        self._t0: float | None = None  # start of the current phase, s
        self._recent: list = []
        self._peak = -np.inf
        self._all: list = []  # every tick: (t, reading, command held before it), for the estimator
        self._t: list = []  # fitted samples: times, readings, the commands held before each
        self._z: list = []
        self._u: list = []

    @property
    def done(self) -> bool:
        """True once the excitation has ended (fitted or failed)."""
        return self.phase == "done"

    def _enter(self, phase: str, t: float) -> None:
        self.phase, self._t0 = phase, t

    def tick(self, t: float, reading_pa: float, held: Command | None = None) -> tuple[Command, bool]:
        """One sample: the command to hold from t (s) on and whether the calibration is over. The
        tick that ends it runs the fit (and the estimator over the excitation): about a second of
        wall time, while the chamber vents. ``held``: the command the rig reports it held over the
        period this reading ends (None = the last one returned, as in a lockstep simulation); the fit
        and the estimator take it, so a link that applies commands a period late does not bias them."""
        s = self.settings
        z = float(reading_pa)
        before = self.command if held is None else held
        if not np.isfinite(t) or (self._all and t <= self._all[-1][0]):
            last = self._all[-1][0] if self._all else None
            raise ValueError(f"calibration.tick: t = {t!r} s must be finite and after the last tick's {last} s")
        if self._t0 is None:
            self._t0 = float(t)
        if self.phase == "done":
            return _VENT, True
        self._all.append((float(t), reading_pa, before))
        el = t - self._t0
        if self.phase != "vent":
            self._t.append(float(t))
            self._z.append(z)
            self._u.append(before.as_array())
        if self.phase == "vent":
            if np.isfinite(z):
                self._recent = (self._recent + [z])[-s.rest_samples:]
            rested = len(self._recent) == s.rest_samples and abs(np.mean(self._recent)) < s.rest_tol
            if el + 1e-9 >= s.vent_min and rested:
                self._enter("pump", t)
                self._t, self._z, self._u = [float(t)], [z], [before.as_array()]
                self.command = Command(s.speed, 1.0, 0.0)
            elif el + 1e-9 >= s.vent_max:
                return self._finish("failed: the chamber did not vent to ambient")
        elif self.phase == "pump":
            # stop on the first reading above p_stop, a missing one (no pumping blind), a fall of
            # LIMIT_FALL_SIGMAS sensor sigmas below the peak (past the membrane's pressure maximum
            # the pressure drops while the cap runs away) or time
            self._peak = max(self._peak, z) if np.isfinite(z) else self._peak
            fell = np.isfinite(z) and z < self._peak - LIMIT_FALL_SIGMAS * s.noise_std
            if not np.isfinite(z) or z > self.p_stop or fell or el + 1e-9 >= s.pump_max:
                self._enter("hold", t)
                self.command = _HOLD
        elif self.phase == "hold":
            if np.isfinite(z) and z > s.p_max:
                return self._finish("failed: pressure above p_max while holding")
            if el + 1e-9 >= s.hold:
                self._enter("vent_end", t)
                self.command = Command(0.0, 0.0, s.vent_duty)
        elif self.phase == "vent_end" and el + 1e-9 >= s.vent_end:
            return self._finish(None)
        return self.command, False

    def _finish(self, failure: str | None) -> tuple[Command, bool]:
        self.phase = "done"
        self.command = _VENT
        if failure is not None:
            self.status = failure
            return _VENT, True
        try:
            self.result = self._fit()
            self.status = "ok"
        except (ValueError, FloatingPointError, RuntimeError, np.linalg.LinAlgError) as exc:
            self.status = f"failed: {exc}"
        if self.estimator is not None:
            self._run_estimator()
        return _VENT, True

    def _run_estimator(self) -> None:
        """The estimator over every tick of the excitation, with the fitted factors (module doc)."""
        est = self.estimator
        hand = self.result is not None and all(n in est.state_names for n in FACTOR_NAMES)
        prior = self.result.floored(self.settings.handover_std_floor) if hand else None
        for i, (t, z, cmd) in enumerate(self._all):
            self.estimate = est.step(t, z, cmd)
            if i == 0 and hand:
                hand_to_estimator(prior, est)
        if hand:
            hand_to_estimator(prior, est)

    # --- the fit ------------------------------------------------------------------------------
    def _simulate(self, factors: np.ndarray) -> np.ndarray:
        """Model pressure (Pa) at the fitted samples for each column of factors (3 x n)."""
        s = self.settings
        csv = str(self.pneumatics.csv_path)
        if self.platform.mass > 0:  # flat under the load: the gas law alone, no membrane law
            fid = make_fidelity("quasi_static", self.actuator.material, csv)
        elif s.membrane == "exact":
            fid = make_exact_free(self.actuator.material, csv)
        else:
            fid = make_fidelity("free", self.actuator.material, csv)
        thetas = np.column_stack([fid.space.values(*scaled(self.actuator, self.pneumatics, *f), self.platform)
                                  for f in factors.T])
        period = s.sample_period
        plant = period_plant(fid, thetas, "rk4", period)
        n = thetas.shape[1]
        p = np.zeros((len(self._t), n))
        p[0] = plant.output("p")
        timing = CommandTiming(period, s.valve_delay, s.sensor_delay)
        timing.acting(self._u[0], 0)
        for i in range(1, len(self._t)):
            dt = self._t[i] - self._t[i - 1]
            u = timing.acting(self._u[i], max(1, int(round(dt / period))))
            plant.advance(np.repeat(u[:, None], n, axis=1), dt)
            if not np.all(plant.alive):
                raise RuntimeError("the model diverged for a trial factor")
            p[i] = plant.output("p")
        return p

    def _fit(self) -> CalibrationResult:
        s = self.settings
        z = np.array(self._z)
        use = np.isfinite(z) & (z < s.sensor_range)
        if use.sum() < 10:
            raise ValueError(f"only {int(use.sum())} readings to fit")
        prior = (np.asarray(s.prior_mean, dtype=float), np.asarray(s.prior_std, dtype=float))
        cache: dict = {}

        def sim(x):
            # the residuals and their forward differences from one batched simulation
            key = tuple(np.round(x, 12))
            if key not in cache:
                cols = np.column_stack([x] + [x + _FD_STEP * e for e in np.eye(3)])
                p = self._simulate(cols)
                r = (z[use] - p[use, 0]) / s.noise_std
                J = -(p[use, 1:] - p[use, :1]) / (_FD_STEP * s.noise_std)
                cache.clear()
                cache[key] = (r, J)
            return cache[key]

        est = identify(lambda x: sim(x)[0], [prior[0].copy()], _BOUNDS, jac=lambda x: sim(x)[1], prior=prior,
                       x_scale=prior[1], max_nfev=20)
        return CalibrationResult(b=float(est.x[0]), k=float(est.x[1]), c=float(est.x[2]), cov=est.cov,
                                 residual_rms=float(np.sqrt(np.mean(est.r ** 2)) * s.noise_std),
                                 n_readings=int(use.sum()), p_peak=float(np.nanmax(z)))


def hand_to_estimator(result: CalibrationResult, estimator, t: float | None = None) -> None:
    """Make the calibration the estimator's prior on its factor states ``b, k, c``: means set,
    variances from ``result.cov``, their correlations with the other states cut (the calibration
    is independent of what the filter saw). The estimator must have stepped at least once and
    expose ``state_names``, ``x``, ``P``, ``s``, ``resting`` and ``reset`` (the EKF, the UKF)."""
    names = tuple(estimator.state_names)
    if not all(n in names for n in FACTOR_NAMES) or estimator.x is None:
        raise ValueError("hand_to_estimator: the estimator has no factor states b, k, c, or has not started")
    idx = [names.index(n) for n in FACTOR_NAMES]
    x = np.array(estimator.x, dtype=float)
    P = np.array(estimator.P, dtype=float)
    x[idx] = result.factors
    P[idx, :] = 0.0
    P[:, idx] = 0.0
    P[np.ix_(idx, idx)] = result.cov
    estimator.reset(estimator.t if t is None else t, x, P, shape=estimator.s, resting=estimator.resting)
