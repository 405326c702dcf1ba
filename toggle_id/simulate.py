"""Batched simulation of the motor-toggle plant: a population of parameter vectors, one record, sampled
x_B and i_q for all of them, and a per-individual status.

>>> from toggle_id.simulate import simulate, FAST
>>> from toggle_id.record import Record
>>> from toggle_id.params import ASSIGNED
>>> res = simulate(ASSIGNED[None, :], Record.from_sweep("simulation"))
>>> res.status.tolist(), res.x_B.shape
([0], (1, 5001))
"""
from __future__ import annotations

import threading
import warnings
from collections.abc import MutableMapping, Sequence
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError
from .kernels import kernel_array
from .kernels import slots as K
from .kernels.driver import (lash_batch_parallel, lash_batch_serial, sensitivities_row, simulate_batch_parallel,
                             simulate_batch_serial)
from .kernels.geometry import build_table
from .kernels.sens import SENS_SLOTS as ANALYTIC_SLOTS  # the slots simulate_sensitivities differentiates
from .params import N_PARAMS
from .plant import GEOMETRY, Geometry
from .record import Record

#: Status codes of a simulation (per individual).
STATUS_OK, STATUS_MODEL_FAILURE, STATUS_SOLVER_FAILURE, STATUS_INVALID = K.OK, K.MODEL_FAILURE, K.SOLVER_FAILURE, K.INVALID_PARAMS
STATUS_NAMES = {STATUS_OK: "ok", STATUS_MODEL_FAILURE: "model failure", STATUS_SOLVER_FAILURE: "solver failure",
                STATUS_INVALID: "invalid parameters"}
N_THETA = K.N_THETA
#: Integration methods: Rodas4 throughout, DOPRI5 throughout, or DOPRI5 in free motion and Rodas4 while clamped.
METHODS = {"rodas4": K.METHOD_RODAS4, "dopri5": K.METHOD_DOPRI5, "mixed": K.METHOD_MIXED}
STOPS = {"none": K.STOPS_NONE, "sampled": K.STOPS_SAMPLED, "all": K.STOPS_ALL}
#: (parallel, backlash) -> the batched kernel: rows with backlash run the two-body integrator, compiled apart.
_KERNELS = {(False, False): simulate_batch_serial, (True, False): simulate_batch_parallel,
            (False, True): lash_batch_serial, (True, True): lash_batch_parallel}

#: The environment under which processes that share the cores with one another all run the parallel kernels
#: (the test suite's workers, several jobs at once): numba's OpenMP threads then sleep while they wait instead of
#: spinning for the cores the other process needs. Measured with ``python -m jobs.bench --shared-cores`` (medians of
#: 5): two processes side by side simulate 17 % (1-s record) and 12 % (5-s) more in total — with OpenMP's default
#: policy two processes do less than one alone — while one process alone does 8 % less on the 1-s record (the same
#: on the 5-s one); so it is not the default of a lone job.
SHARED_CORES_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}


def share_cores(env: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """Set :data:`SHARED_CORES_ENV` in ``env`` (``os.environ`` or a child process's) where the user has not set its
    variables; returns ``env``. Acts only on a process whose parallel kernels have not run yet: OpenMP reads it
    when numba first loads its threads."""
    for key, value in SHARED_CORES_ENV.items():
        env.setdefault(key, value)
    return env


_COUNT_LOCK = threading.Lock()
_SIMULATIONS = 0


def simulations_run() -> int:
    """How many parameter vectors :func:`simulate` has been asked to simulate in this process so far (each row of
    each call counts once, fallback re-integrations not again). Differences of it measure what a piece of work
    cost in simulations (e.g. a polish, or the discovery loop); work done in other processes (Ray actors) is not
    counted here."""
    return _SIMULATIONS


@dataclass(frozen=True)
class SolverSettings:
    """Adaptive integrator settings: relative tolerance, absolute tolerances on (q rad, q̇ rad/s, i_q A), first
    step and largest step (s), the step budget per simulation (accepted + rejected steps; beyond it: solver
    failure) and the method (see :data:`METHODS`): ``rodas4`` (linearly implicit, stable in the stiff clamped
    mode and in stiff corners of the domain such as L_q → 0; the fast tier), ``dopri5`` (explicit, cheapest
    per step where accuracy keeps the steps small anyway; the precise tier) or ``mixed`` (DOPRI5 in free
    motion, Rodas4 while clamped)."""

    rtol: float = 1e-5
    atol_q: float = 1e-8
    atol_w: float = 1e-4
    atol_i: float = 1e-2
    h0: float = 1e-4
    hmax: float = 5e-2
    max_steps: int = 50_000
    method: str = "rodas4"
    #: where a step ends at every output sample and, for a sampled input, at every input sample (shifted by the
    #: dead time), so that no step straddles a kink of the linearly interpolated input and every output is a
    #: step's end, not an interpolation (see :data:`STOPS`): ``none``, ``sampled`` (on an input given by its
    #: samples, a record read from a file; the precise tiers: far smoother in the parameters and no dearer) or
    #: ``all`` (a swept sine too: 12-22x smoother there, but 36 % dearer; ``python -m jobs.bench_stops``)
    stops: str = "none"
    #: rows that exhaust ``max_steps`` are integrated again with these settings (None: they fail)
    fallback: "SolverSettings | None" = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(f"unknown integration method {self.method!r}; known: {', '.join(METHODS)}")
        if self.stops not in STOPS:
            raise ConfigError(f"unknown stops {self.stops!r}; known: {', '.join(STOPS)}")
        if not (self.rtol > 0 and self.atol_q > 0 and self.atol_w > 0 and self.atol_i > 0):
            raise ConfigError("solver tolerances must be positive")
        if not (self.h0 > 0 and self.hmax > 0 and self.max_steps >= 1):
            raise ConfigError("h0, hmax must be positive and max_steps at least 1")

    def as_array(self) -> np.ndarray:
        return np.array([self.rtol, self.atol_q, self.atol_w, self.atol_i, self.h0, self.hmax,
                         float(self.max_steps), float(METHODS[self.method]), float(STOPS[self.stops])], dtype=float)


#: Fast tier (the GA): Rodas4, x_B within 0.3 µm of the references (about 580 steps for a 5-s record).
#: Precise tier (polish, finite-difference sensitivities, residuals): DOPRI5 at tight tolerances, x_B within
#: 1e-5 µm of the references; on a record given by its samples its steps stop at them, so it is smooth in the
#: parameters there too: a forward difference at a relative step of 1e-4 lies within ~1e-3 of the exact one on
#: every column (4e-3 with a backlash), where stepping freely across the samples left up to 14× a column's norm —
#: the input's kinks and the interpolated outputs made the step selection jitter (``python -m jobs.bench_stops``;
#: on a continuous swept sine it steps freely: within 1 % at worst, 36 % cheaper than with stops). A stiff
#: candidate (large D or K_l, small L_q) makes DOPRI5 crawl at its stability limit: past 20 000 steps
#: (a normal 5-s record takes 10 000-16 000) the row is redone by Rodas4 at rtol 1e-9 (as exact, less smooth).
FAST = SolverSettings()
PRECISE_STIFF = SolverSettings(rtol=1e-9, atol_q=1e-11, atol_w=1e-8, atol_i=1e-5, hmax=2e-3, max_steps=500_000,
                               method="rodas4", stops="sampled")
PRECISE = SolverSettings(rtol=1e-10, atol_q=1e-12, atol_w=1e-9, atol_i=1e-6, hmax=2e-3, max_steps=20_000,
                         method="dopri5", stops="sampled", fallback=PRECISE_STIFF)
#: Jacobian tier (finite-difference Jacobians of PRECISE polishes, beside PRECISE residuals, where a setting's
#: ``fd_tier`` asks for it): DOPRI5 100× looser than PRECISE, about half its cost, steps stopping at a sampled
#: input's samples too; its forward differences at a relative step of 1e-4 lie within ~2 % of the exact ones on
#: the sampled sweeps and ~20 % on the cycling command (stepping freely: many times a column's norm there, 8 % on
#: a continuous sweep). Its fixed point lies
#: off the optimum along sloppy directions, which moved discovery verdicts (README): the defaults use it only
#: in the fast method's finalists.
JACOBIAN_STIFF = SolverSettings(rtol=1e-7, atol_q=1e-9, atol_w=1e-6, atol_i=1e-3, hmax=2e-3, max_steps=500_000,
                                method="rodas4", stops="sampled")
JACOBIAN = SolverSettings(rtol=1e-8, atol_q=1e-10, atol_w=1e-7, atol_i=1e-4, hmax=2e-3, max_steps=20_000,
                          method="dopri5", stops="sampled", fallback=JACOBIAN_STIFF)
#: relative forward-difference step of a Jacobian in the :data:`JACOBIAN` tier
JACOBIAN_REL_STEP = 1e-3
TIERS = {"fast": FAST, "precise": PRECISE}

#: The integrators a PRECISE polish's finite-difference Jacobian may use (``fd_tier`` of the polish and discovery
#: settings): ``jacobian`` (:data:`JACOBIAN` at :data:`JACOBIAN_REL_STEP`) or ``precise`` (the residuals' own tier,
#: at the settings' ``fd_rel_step``).
FD_TIERS = ("jacobian", "precise")


def precise_jacobian(fd_tier: str, fd_rel_step: float) -> tuple[SolverSettings, float]:
    """The integrator and relative step of a PRECISE polish's finite-difference Jacobian (see :data:`FD_TIERS`)."""
    if fd_tier == "jacobian":
        return JACOBIAN, JACOBIAN_REL_STEP
    if fd_tier == "precise":
        return PRECISE, fd_rel_step
    raise ConfigError(f"fd_tier must be one of {', '.join(FD_TIERS)}, got {fd_tier!r}")


@dataclass
class SolverChoice:
    """The ``solver`` node of a job's configuration: which tier of :data:`TIERS` simulates the GA's
    populations. The polish, the sensitivities and the residuals always use PRECISE."""

    ga_tier: str = "fast"  # fast | precise


@dataclass
class SimResult:
    """x_B (P, N) in m and i_q (P, N) in A at the record's samples; ``status`` (P,) codes (0 = ok); rows that
    failed hold NaN. ``n_steps`` accepted+rejected integrator steps; ``contact`` (P, 4): first contact instant
    (s, inf if none) and the state (q, q̇, i_q) there; ``fell_back`` (P,): rows integrated again by the
    settings' fallback after the primary method exhausted its step budget."""

    x_B: np.ndarray
    i_q: np.ndarray
    status: np.ndarray
    n_steps: np.ndarray
    contact: np.ndarray
    fell_back: np.ndarray | None = None

    @property
    def ok(self) -> np.ndarray:
        return self.status == STATUS_OK

    def status_counts(self) -> dict[str, int]:
        return {STATUS_NAMES[c]: int(np.sum(self.status == c)) for c in STATUS_NAMES}


def extend(theta: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
    """(P, 15) physical parameters → (P, N_THETA) kernel vectors with the effect parameters at their 'off'
    defaults (see :mod:`toggle_id.effects`), or taken from ``extra`` (P or 1, N_THETA − 15)."""
    from .effects import (
        EXTRA_DEFAULTS,  # late import: effects imports this module's constants
    )

    theta = np.atleast_2d(np.asarray(theta, dtype=float))
    if theta.shape[1] == N_THETA:
        return np.ascontiguousarray(theta)
    if theta.shape[1] != N_PARAMS:
        raise ValueError(f"parameter vectors must have {N_PARAMS} (or {N_THETA}) columns, got {theta.shape[1]}")
    out = np.empty((theta.shape[0], N_THETA))
    out[:, :N_PARAMS] = theta
    out[:, N_PARAMS:] = EXTRA_DEFAULTS if extra is None else extra
    return out


_TABLES: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def geometry_table(geometry: Geometry = GEOMETRY, dq: float = 5e-4) -> tuple[np.ndarray, np.ndarray]:
    """Cubic-Hermite table of the q-only kinematics, built once per geometry and shared by all individuals.

    It spans the crank angles where link 5 is well away from its singular (|sin θ5| → 1) end; outside it the
    kernel falls back to the closed form. Returns (table (n, 20), header [q_lo, 1/dq, n, dq]).
    """
    key = (tuple(geometry.as_array()), dq)
    if key not in _TABLES:
        # |sin θ5| ≤ 0.9  ⇔  sin(q + φ) ≥ (h − 0.9 r5) / r4
        q_lo = float(np.arcsin((geometry.h - 0.9 * geometry.r5) / geometry.r4) - geometry.phi)
        q_hi = float(np.arccos(0.0)) - 1e-6
        n = int((q_hi - q_lo) / dq) + 1
        tab = build_table(geometry.as_array(), q_lo, dq, n)
        _TABLES[key] = (tab, np.array([q_lo, 1.0 / dq, float(n), dq]))
    return _TABLES[key]


def _invalid_rows(thetas: np.ndarray, geo: Geometry) -> np.ndarray:
    """Rows that cannot define a plant: non-finite, negative, L_q ≤ 0, or no inertia at all."""
    phys = thetas[:, :N_PARAMS]
    bad = ~np.all(np.isfinite(thetas), axis=1)
    bad |= np.any(phys < 0.0, axis=1)
    bad |= ~(thetas[:, K.L_Q] > 0.0)
    inertia = thetas[:, [K.M2, K.M3, K.M5, K.MB, K.MC, K.J_M]].sum(axis=1)
    bad |= ~(inertia > 0.0)
    return bad


def _kernel_record(record: Record, geometry: Geometry, start: tuple[float, Sequence[float], int] | None = None):
    """The kernels' view of a record and its start: geometry array, t, v_in, the sweep's description (zeros for a
    sampled input) and (t0, y0, contact0) — by default at rest at the record's x_B0."""
    if start is None:
        start = (float(record.t[0]), (geometry.q_of_xB(record.x_B0), 0.0, 0.0), int(record.x_B0 >= geometry.x_B_L))
    t0, y0, contact0 = start
    sweep = record.sweep.as_array() if record.sweep is not None else np.zeros(5)
    return (geometry.as_array(), kernel_array(record.t), kernel_array(record.v_in), sweep,
            (float(t0), kernel_array(y0), int(contact0)))


def simulate(theta: np.ndarray, record: Record, settings: SolverSettings = FAST, *, n_samples: int | None = None,
             start: tuple[float, Sequence[float], int] | None = None, parallel: bool = False,
             geometry: Geometry = GEOMETRY) -> SimResult:
    """Simulate every row of ``theta`` ((P, 15) physical or (P, N_THETA) extended) on ``record``.

    ``n_samples`` limits the output (and the integration) to the first samples (stage 1 needs only the
    pre-clamp part). ``start = (t0, (q, q̇, i_q), contact)`` restarts from a known state (stage 2 reuses the
    shared pre-contact trajectory); samples before t0 are NaN. Never raises for bad parameter values: each
    row gets a status.
    """
    global _SIMULATIONS
    thetas = kernel_array(extend(theta))
    P = thetas.shape[0]
    with _COUNT_LOCK:
        _SIMULATIONS += P
    N = record.n if n_samples is None else int(n_samples)
    if not 1 <= N <= record.n:
        raise ValueError(f"n_samples must be in [1, {record.n}], got {n_samples}")
    geo, t, v_in, sweep, (t0, y0, contact0) = _kernel_record(record, geometry, start)
    x = np.empty((P, record.n))
    i = np.empty((P, record.n))
    status = np.zeros(P, dtype=np.int8)
    n_steps = np.zeros(P, dtype=np.int64)
    events = np.full((P, 4), np.nan)
    fell_back = np.zeros(P, dtype=bool)
    bad = _invalid_rows(thetas, geometry)
    status[bad] = STATUS_INVALID
    x[bad] = np.nan
    i[bad] = np.nan
    good = np.flatnonzero(~bad)
    if good.size:
        tab, head = geometry_table(geometry)

        def run(rows: np.ndarray, tier: SolverSettings) -> None:
            lash = thetas[rows, K.B_L] > 0.0  # backlash: the two-body integrator, compiled apart (kernels.driver)
            for is_lash, part in ((False, rows[~lash]), (True, rows[lash])):
                if part.size:
                    args = (geo, tab, head, t, N, v_in, sweep, record.sweep is not None, float(t0), y0,
                            int(contact0), tier.as_array(), x, i, status, n_steps, events)
                    try:
                        _KERNELS[parallel, is_lash](thetas, part, *args)
                    except Exception as exc:  # a kernel's numerical corner must not end a job: its rows fail
                        _rows_apart(_KERNELS[False, is_lash], thetas, part, args, (x, i, status), exc)

        run(good, settings)
        redo = np.flatnonzero(status == STATUS_SOLVER_FAILURE)
        if redo.size and settings.fallback is not None:
            fell_back[redo] = True
            run(redo, settings.fallback)
    return SimResult(x_B=x, i_q=i, status=status, n_steps=n_steps, contact=events, fell_back=fell_back)


def _rows_apart(kern, thetas: np.ndarray, rows: np.ndarray, args: tuple,
                outputs: tuple[np.ndarray, np.ndarray, np.ndarray], exc: Exception) -> None:
    """After a batch's kernel raised ``exc``: each row again on its own (the kernel's other arguments ``args``), and
    a row that raises too is a solver failure (its ``outputs`` x_B, i_q NaN and its status set), with one warning
    naming the exception — a failed simulation is data, not a crash."""
    x, i, status = outputs
    failed = []
    for r in rows:
        try:
            kern(thetas, np.array([r]), *args)
        except Exception:
            status[r] = STATUS_SOLVER_FAILURE
            x[r], i[r] = np.nan, np.nan
            failed.append(int(r))
    warnings.warn(f"the simulation kernel raised {type(exc).__name__} ({exc}) on a batch of {rows.size} rows; "
                  f"{len(failed)} of them fail on their own and are marked solver failures", RuntimeWarning,
                  stacklevel=3)


@dataclass
class SensResult:
    """One vector's simulation and the derivatives of its x_B w.r.t. the slots asked for: ``x_B``, ``i_q`` (N,),
    ``dx`` (len(slots), N) in m per unit of each parameter, NaN when ``status`` (the simulation's) is not OK or
    ``sens_status`` (the replay's) is not; ``n_steps`` the simulation's steps; ``fell_back``: simulated on the
    settings' fallback after their step budget ran out."""

    x_B: np.ndarray
    i_q: np.ndarray
    dx: np.ndarray
    status: int
    sens_status: int
    n_steps: int
    fell_back: bool = False

    @property
    def ok(self) -> bool:
        return self.status == STATUS_OK and self.sens_status == STATUS_OK


def simulate_sensitivities(theta: np.ndarray, record: Record, settings: SolverSettings, slots: Sequence[int], *,
                           geometry: Geometry = GEOMETRY, threads: int = 2) -> SensResult:
    """Simulate one extended vector ``theta`` without backlash on ``record`` and differentiate x_B w.r.t. the
    extended-vector ``slots`` (all in :data:`ANALYTIC_SLOTS`) along its steps (:mod:`toggle_id.kernels.sens`), in
    about the time of a few simulations whatever the number of slots; ``threads`` groups of columns are retraced
    side by side. A row that exhausts the settings' step budget is done again on their fallback, as
    :func:`simulate` does (``fell_back``). x_B and i_q are those :func:`simulate` gives for the same vector and
    settings, bit for bit. Bad parameter values give a status, never an exception."""
    slots = np.asarray(slots, dtype=np.int64)
    unknown = sorted(set(slots.tolist()) - ANALYTIC_SLOTS)
    if unknown:
        raise ConfigError(f"simulate_sensitivities cannot differentiate the slots {unknown}")
    th = kernel_array(extend(theta))
    if th.shape[0] != 1:
        raise ValueError(f"simulate_sensitivities takes one parameter vector, got {th.shape[0]}")
    global _SIMULATIONS
    with _COUNT_LOCK:
        _SIMULATIONS += 1
    N = record.n
    x = np.full(N, np.nan)
    i = np.full(N, np.nan)
    dx = np.full((slots.size, N), np.nan)
    if _invalid_rows(th, geometry)[0]:
        return SensResult(x, i, dx, STATUS_INVALID, STATUS_INVALID, 0, False)
    if th[0, K.B_L] > 0.0:
        raise ConfigError("simulate_sensitivities: a vector with backlash goes to the two-body integrator, "
                          "which has no sensitivities")
    geo, t, v_in, sweep, (t0, y0, contact0) = _kernel_record(record, geometry)
    tab, head = geometry_table(geometry)

    def run(tier: SolverSettings):
        return sensitivities_row(th[0], geo, tab, head, t, N, v_in, sweep, record.sweep is not None, t0, y0, contact0,
                                 tier.as_array(), x, i, slots, dx, max(1, min(int(threads), slots.size)))

    st, ns, sst = run(settings)
    fell_back = st == STATUS_SOLVER_FAILURE and settings.fallback is not None
    if fell_back:
        st, ns, sst = run(settings.fallback)
    if st != STATUS_OK:
        x[:] = np.nan
        i[:] = np.nan
    if st != STATUS_OK or sst != STATUS_OK:
        dx[:] = np.nan
    return SensResult(x, i, dx, int(st), int(sst), int(ns), bool(fell_back))


def compile_kernels(kinds: Sequence[str] = ("rigid", "lash"), parallel: bool = True) -> None:
    """Compile the batched kernels of ``kinds`` — ``"rigid"``, ``"lash"`` (backlash), ``"sens"`` (the rigid
    integrator's forward sensitivities) — serial and, with ``parallel``, threaded, by a 3-sample simulation each; on
    a warm numba cache this only loads them. For a process that wants the compilation over before its work is timed
    or shared: the test suite compiles them in two processes side by side before its workers start, where each
    worker would otherwise compile them all."""
    from .params import ASSIGNED

    unknown = set(kinds) - {"rigid", "lash", "sens"}
    if unknown:
        raise ConfigError(f"compile_kernels: unknown kinds {sorted(unknown)}; known: rigid, lash, sens")
    record = Record.from_sweep("simulation", 0.01, name="compile")
    for kind in kinds:
        theta = extend(ASSIGNED[None, :])
        if kind == "sens":
            simulate_sensitivities(theta[0], record, PRECISE, [K.K_T])
            continue
        theta[0, K.B_L] = 1e-4 if kind == "lash" else 0.0
        for par in (False, True) if parallel else (False,):
            simulate(theta, record, FAST, n_samples=3, parallel=par)
