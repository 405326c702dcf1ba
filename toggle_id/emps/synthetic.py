"""Simulated EMPS records: a smooth back-and-forth reference and the closed loop driven by a chosen model.

They stand in for the benchmark's records where those are absent (tests, examples): the same controller, drive
gain and sampling as the benchmark (:mod:`.data` constants), the position quantised like the rig's encoder
(5e-8 m on the load side), and optionally a pulse train entering at the controller output as in
``DATA_EMPS_PULSES.mat``. The truth is known, so a fit on such a record can be checked against it.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..errors import ConfigError
from .data import DT, GTAU, KP, KV, V_SAT, EmpsRecord

#: Load-side position quantum of the rig (m): 2.5 mm per motor revolution over 50 000 counts.
POSITION_QUANTUM = 5e-8


def smoothstep5(x: np.ndarray) -> np.ndarray:
    """Quintic smoothstep 10x³ − 15x⁴ + 6x⁵ on [0, 1] (zero velocity and acceleration at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def back_and_forth(n: int, dt: float = DT, waypoints: Sequence[float] = (0.0, 0.12, 0.2, 0.08, 0.0),
                   move_s: float = 0.9, dwell_s: float = 0.15) -> np.ndarray:
    """Reference position q_r (m) on ``n`` samples: quintic moves between ``waypoints`` (m), each ``move_s`` s long
    and followed by a ``dwell_s`` s standstill, repeated (forth and back) until the record is full."""
    if n < 3 or dt <= 0 or move_s <= 0 or dwell_s < 0 or len(waypoints) < 2:
        raise ConfigError("back_and_forth needs n >= 3, dt > 0, move_s > 0, dwell_s >= 0 and two waypoints")
    t = np.arange(n) * dt
    pts = list(waypoints)
    seg = move_s + dwell_s
    k = np.floor(t / seg).astype(int)  # segment index
    tau = (t - k * seg) / move_s
    cycle = len(pts) - 1
    j = k % cycle
    start = np.array([pts[i] for i in j])
    end = np.array([pts[i + 1] for i in j])
    return start + (end - start) * smoothstep5(tau)


def pulse_train(n: int, period: int = 1000, width: int = 500, start: int = 343, amplitude: float = 5.0
                ) -> np.ndarray:
    """Rectangular pulses like DATA_EMPS_PULSES' ``pulses_N``: ``amplitude`` for ``width`` samples every ``period``
    samples from sample ``start`` (the benchmark's: 5 every 1000 samples for 500, from sample 344)."""
    k = np.arange(n)
    on = (k >= start) & (((k - start) % period) < width)
    return np.where(on, float(amplitude), 0.0)


def simulated_record(theta: np.ndarray | Mapping[str, float], n: int = 4000, *, qg: np.ndarray | None = None,
                     pulses: np.ndarray | None = None, pulse_gain: float = 1.0,
                     quantum: float = POSITION_QUANTUM, noise_m: float = 0.0, seed: int = 0,
                     name: str = "simulated", sim_options: Mapping | None = None) -> EmpsRecord:
    """An EMPS record simulated in closed loop by :func:`toggle_id.emps.model.simulate_emps` with the model
    ``theta`` on the reference ``qg`` (default :func:`back_and_forth`): ``vir`` is the simulated controller output
    (V, pulses included), ``qm`` the simulated position plus optional white noise (``noise_m``, m) rounded to
    ``quantum`` (m; 0 keeps it exact), ``pulses`` the given train (added to the controller output times
    ``pulse_gain``). Constants: the benchmark's gtau, kp, kv, 1 kHz, 10 V."""
    from .model import simulate_emps

    qg = back_and_forth(n) if qg is None else np.asarray(qg, dtype=float)
    n = qg.size
    t = np.arange(n) * DT
    base = EmpsRecord(t=t, vir=np.zeros(n), qm=np.full(n, qg[0]), qg=qg, pulses=pulses, gtau=GTAU, kp=KP, kv=KV,
                      dt=DT, v_sat=V_SAT, name=name)
    opts = {**dict(sim_options or {}), "pulse_gain": pulse_gain}
    sim = simulate_emps(theta, base, **opts)
    if sim.status[0] != 0:
        raise ConfigError(f"the model could not be simulated (status {int(sim.status[0])})")
    q = sim.q[0].copy()
    if noise_m > 0:
        q += np.random.default_rng(seed).normal(0.0, noise_m, n)
    if quantum > 0:
        q = np.round(q / quantum) * quantum
    return EmpsRecord(t=t, vir=sim.nu[0], qm=q, qg=qg, pulses=base.pulses, gtau=GTAU, kp=KP, kv=KV, dt=DT,
                      v_sat=V_SAT, name=name, meta={"source": "simulated", "theta": np.asarray(theta).tolist()
                                                    if not isinstance(theta, Mapping) else dict(theta)})


def write_record(record: EmpsRecord, path: str, fmt: str | None = None) -> str:
    """Write a record as the benchmark's ``.mat`` layout (keys t, vir, qm, qg, pulses_N, gtau, kp, kv; column
    vectors) or as a ``.csv`` (t,vir,qm,qg,pulses_N; ``%.17g``), by ``fmt`` or the file's suffix; returns the path."""
    from pathlib import Path

    p = Path(path)
    fmt = (fmt or p.suffix.lstrip(".")).lower()
    cols = {"t": record.t, "vir": record.vir, "qm": record.qm, "qg": record.qg, "pulses_N": record.pulses}
    if fmt == "mat":
        from scipy.io import savemat

        savemat(str(p), {**{k: v[:, None] for k, v in cols.items()}, "gtau": record.gtau, "kp": record.kp,
                         "kv": record.kv})
    elif fmt == "csv":
        np.savetxt(p, np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols), comments="",
                   fmt="%.17g")
    else:
        raise ConfigError(f"write_record: unknown format {fmt!r}; expected mat or csv")
    return str(p)
