"""The record(s) a job works on, from the ``data`` node of its configuration.

A simulated record (conf/data/simulated.yaml) is the PRECISE response of a truth (assigned values, ``params`` and
``effects`` overrides) with a measurement noise model; a CSV record (conf/data/csv.yaml) is read and checked by
:func:`toggle_id.data.read_csv`; a joint node (conf/data/joint.yaml) lists several of either. Every bad value is a
one-line :class:`~toggle_id.errors.ConfigError` before any simulation.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from .. import params as P
from ..data import read_csv
from ..effects import ALL_INDEX, ALL_NAMES
from ..errors import ConfigError
from ..record import COMMANDS, CYCLING, SWEEPS, Record, measure
from ..simulate import PRECISE, extend, simulate


def truth_vector(data: Mapping) -> np.ndarray:
    """Extended parameter vector of a simulated record's truth (assigned values + overrides + effects)."""
    theta = extend(P.ASSIGNED)[0]
    for group in ("params", "effects"):
        for name, value in (data.get(group) or {}).items():
            if value is None:  # null: the assigned value / effect off
                continue
            if name not in ALL_INDEX:
                raise ConfigError(f"data.{group}: unknown parameter {name!r}; known: {', '.join(ALL_NAMES)}")
            theta[ALL_INDEX[name]] = float(value)
    return theta


def _number(data: Mapping, key: str, default: float) -> float:
    """``data[key]`` as a float (``default`` when absent or null); one-line ConfigError otherwise."""
    value = data.get(key, default)
    if value is None:
        value = default
    if isinstance(value, bool):
        raise ConfigError(f"data.{key} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"data.{key} must be a number, got {value!r}") from None


def build_record(data: Mapping) -> tuple[Record, np.ndarray | None]:
    """The record a job works on and, for simulated records, the true extended parameter vector.

    A simulated record (``source: simulated``, conf/data/simulated.yaml) is driven by ``command``: ``sweep``
    (the paper's swept sine named by ``sweep``, in continuous time) or ``cycling`` (the open/close cycling
    command :data:`toggle_id.record.CYCLING`, defined by its samples). Its x_B is the PRECISE simulation of the
    truth plus Gaussian noise of standard deviation ``noise_m`` — white, or AR(1) with lag-1 coefficient
    ``noise_ar`` ∈ [0, 1) at the same marginal σ — with gross errors of standard deviation ``outlier_m`` on a
    fraction ``outlier_fraction`` of the samples (0: none), rounded to multiples of ``quantum_m`` (an encoder;
    0: off).
    """
    source = data.get("source")
    if source == "joint":
        raise ConfigError("data=joint (several records) is for the identify job (python -m jobs.run "
                          "+experiment=joint); this job works on one record")
    if source == "csv":
        path = data.get("path")
        if not path or path == "???":
            raise ConfigError("data.path must name a CSV file (data=csv data.path=FILE.csv)")
        return read_csv(path, x_B0=data.get("x_B0")), None
    if source != "simulated":
        raise ConfigError(f"unknown data.source {source!r}; known: simulated, csv")
    command = data.get("command", "sweep") or "sweep"
    if command not in COMMANDS:
        raise ConfigError(f"unknown data.command {command!r}; known: {', '.join(COMMANDS)}")
    sweep = data.get("sweep", "simulation")
    if command == "sweep" and sweep not in SWEEPS:
        raise ConfigError(f"unknown data.sweep {sweep!r}; known: {', '.join(SWEEPS)}")
    noise_model(data)  # checked before any simulation
    duration, rate = _number(data, "duration", 5.0), _number(data, "rate_hz", 1000.0)
    x_B0 = _number(data, "x_B0", 0.020)
    try:
        if command == "cycling":
            rec = Record.from_cycling(CYCLING, duration, rate, x_B0=x_B0, name="simulated_cycling")
        else:
            rec = Record.from_sweep(sweep, duration, rate, x_B0=x_B0, name=f"simulated_{sweep}")
    except ValueError as err:
        raise ConfigError(f"data: {err}") from err
    theta = measure_truth(rec, data)
    rec.meta["command"] = (CYCLING.to_dict() if command == "cycling" else
                           {"kind": "sweep", "sweep": sweep, **SWEEPS[sweep].__dict__})
    return rec, theta


#: The noise options of a simulated record: key -> (upper bound, exclusive; None: none), what the value must be.
_NOISE_OPTIONS = {
    "noise_m": (None, "a non-negative number"),
    "noise_ar": (1.0, "an AR(1) coefficient in [0, 1)"),
    "quantum_m": (None, "a non-negative number (m; 0: no quantisation)"),
    "outlier_fraction": (1.0, "a fraction of the samples in [0, 1)"),
    "outlier_m": (None, "a non-negative number (m; 0: no gross errors)"),
}


def noise_model(data: Mapping) -> dict:
    """{noise_m, noise_ar, quantum_m, outlier_fraction, outlier_m, seed} of a simulated record's ``data`` node,
    checked (one-line ConfigError)."""
    out = {}
    for key, (upper, what) in _NOISE_OPTIONS.items():
        value = _number(data, key, 0.0)
        if not (np.isfinite(value) and value >= 0.0 and (upper is None or value < upper)):
            raise ConfigError(f"data.{key} must be {what}, got {value}")
        out[key] = value
    seed = data.get("noise_seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"data.noise_seed must be a non-negative integer, got {seed!r}")
    return {**out, "seed": int(seed)}


def measure_truth(rec: Record, data: Mapping) -> np.ndarray:
    """Fill the input-only record ``rec`` with the PRECISE response of ``data``'s truth (params, effects): x_B
    with its noise model (:func:`noise_model`), i_q noiseless, the truth and noise in ``meta``. Returns the
    truth's extended vector."""
    noise = noise_model(data)
    theta = truth_vector(data)
    sim = simulate(theta[None, :], rec, PRECISE)
    if sim.status[0] != 0:
        raise ConfigError(f"the truth of data.params/effects cannot be simulated under {rec.name!r} "
                          f"({sim.status_counts()})")
    rec.x_B = measure(sim.x_B[0], **noise)
    rec.i_q = sim.i_q[0].copy()
    sigma, rho = noise["noise_m"], noise["noise_ar"]
    brief = {"model": "none" if sigma == 0 else "ar1" if rho > 0 else "white", "sigma_m": sigma, "ar": rho,
             "quantum_m": noise["quantum_m"]}
    if noise["outlier_fraction"] and noise["outlier_m"]:
        brief.update(outlier_fraction=noise["outlier_fraction"], outlier_m=noise["outlier_m"])
    rec.meta.update({"truth": {n: float(v) for n, v in zip(ALL_NAMES, theta)}, "noise_m": sigma, "noise": brief})
    return theta


#: Keys of a joint data node that are not defaults of its records.
_JOINT_OWN_KEYS = ("source", "records")


def build_records(data: Mapping) -> tuple[list[Record], np.ndarray | None]:
    """The records a job fits and their shared truth (None unless all are simulated from the same vector).

    ``data.source: joint`` (conf/data/joint.yaml) lists the records under ``records:``; each item is a
    simulated-record spec (keys of conf/data/simulated.yaml) or a CSV spec (``source: csv``, ``path``). The
    joint node's other keys (``duration``, ``noise_m``, ``params``, …) are defaults for every item; an item's
    ``params``/``effects`` update the shared ones. Any other source gives a one-record list.
    """
    if data.get("source") != "joint":
        record, truth = build_record(data)
        return [record], truth
    items = data.get("records")
    if not isinstance(items, (list, tuple)) or not items:
        raise ConfigError("data.records must list at least one record (data=joint), e.g. "
                          "[{sweep: simulation}, {sweep: experiment}]")
    shared = {k: v for k, v in data.items() if k not in _JOINT_OWN_KEYS}
    records, truths = [], []
    for i, item in enumerate(items):
        if not isinstance(item, Mapping):
            raise ConfigError(f"data.records[{i}] must be a mapping of record settings, got {item!r}")
        spec = {"source": "simulated", **shared}
        for key, value in item.items():
            if key in ("params", "effects") and isinstance(value, Mapping):
                spec[key] = {**(shared.get(key) or {}), **value}
            else:
                spec[key] = value
        if spec.get("source") not in ("simulated", "csv"):
            raise ConfigError(f"data.records[{i}]: unknown source {spec.get('source')!r}; known: simulated, csv")
        try:
            record, truth = build_record(spec)
        except ConfigError as err:
            raise ConfigError(f"data.records[{i}]: {err}") from err
        if item.get("name"):
            record.name = str(item["name"])
        records.append(record)
        truths.append(truth)
    names = [r.name for r in records]
    for i, r in enumerate(records):  # distinct names for the report and the figures
        if names.count(r.name) > 1:
            r.name = f"{r.name}_{i}"
    shared_truth = truths[0]
    if any(t is None for t in truths) or any(not np.array_equal(t, shared_truth) for t in truths[1:]):
        shared_truth = None
    return records, shared_truth
