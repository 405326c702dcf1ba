"""The records of the adversarial set of :mod:`jobs.bench_adversarial`: the truth of each, its response, its noise,
and the records and manifest written.

Every record has its own truth: the 15 physical parameters drawn log-normally around
Table 1 (per record a spread σ_log ∈ [0.15, 0.40], each log-factor σ_log·z with z ~ N(0, 1) cut at ±2.5; a draw
outside the feasible domain of docs/model.md §6, or that its command cannot drive into the clamp and back within the
stroke, is redrawn — the manifest counts the redraws), and one of three commands: the paper's simulation sweep
(A = 0.05 V), its experiment sweep (A = 0.25 V) or the open/close cycling command
(:data:`toggle_id.record.CYCLING`). Noise σ = 1 µm unless the record is about the noise.

What the set holds (one :class:`~jobs.adversarial_specs.Spec` per record), the records' public names and the
calibrated magnitudes: :mod:`jobs.adversarial_specs`.

The verdicts: *exact* (on a mixed record: the library effects named and the rest called unexplained; *+outside-missed*
when the rest is not flagged); *ambiguous-correct* (nothing wrong named, and each true effect reported among a group of
effects the record cannot tell apart); *spurious* / *missed*; for a record outside the library *unexplained-correct*
(nothing named, structure flagged), *missed* (nothing named, no structure flagged) or *ambiguous-wrong* (nothing named,
but library effects offered as the alternatives).

``--duration`` shortens the records (tests); the calibration holds for 5-s records only.
"""
from __future__ import annotations

import hashlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from jobs.adversarial_specs import (
    BUMP_AT,
    BUMP_WIDTH,
    COMBINED_RATIO,
    COMPLIANCE_ZETA,
    DURATION,
    KEYS_BY_NAME,
    NAMES,
    SCALE_PHASE,
    SCALE_PITCH,
    SIGMA,
    SPECS,
    SPECS_BY_KEY,
    Spec,
)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "tests") not in sys.path:
    sys.path.insert(0, str(ROOT / "tests"))  # the independent plant with effects outside the library


# ------------------------------------------------------------------------------------------ truths and records
def base_record(command: str, duration: float):
    """An input-only record of ``command`` (simulation / experiment sweep, or cycling)."""
    from toggle_id.record import Record

    if command == "cycling":
        return Record.from_cycling(duration=duration)
    return Record.from_sweep(command, duration)


def _valid_truth(theta: np.ndarray, command: str) -> bool:
    """In the feasible domain, simulable on its 5-s command, into the clamp (stage 1 of ≥ 30 samples) and, for
    the cycling command, out of it again at least twice, never below 8 mm."""
    from toggle_id.params import LOWER, UPPER
    from toggle_id.simulate import PRECISE, extend, simulate

    if np.any(theta <= LOWER) or np.any(theta >= UPPER):
        return False
    rec = base_record(command, DURATION)
    sim = simulate(extend(theta), rec, PRECISE)
    if sim.status[0] != 0:
        return False
    from toggle_id.excite.inputs import clamp_check

    return clamp_check(sim.x_B[0], 0.056, x_B_min=0.008, clamp_margin=3e-4, min_clamp_samples=30,
                       min_exits=2 if command == "cycling" else 0) == "ok"


def draw_truth(spec: Spec, draw: int = 0) -> tuple[np.ndarray, dict]:
    """The record's 15 physical parameters (seeded by ``spec.seed``) and how they were drawn; ``draw`` k > 0: the
    k-th held-out machine of the spec (:data:`DRAW_SEED_STEP`), drawn the same way from another seed."""
    from toggle_id.params import ASSIGNED

    if draw < 0:
        raise ValueError(f"draw must be >= 0, got {draw}")
    rng = np.random.default_rng([spec.seed, 1] if draw == 0 else [spec.seed, 1, draw])
    for attempt in range(200):
        s = float(rng.uniform(0.15, 0.40))
        z = np.clip(rng.standard_normal(ASSIGNED.size), -2.5, 2.5)
        theta = ASSIGNED * np.exp(s * z)
        if _valid_truth(theta, spec.command):
            return theta, {"sigma_log": s, "log_factors": [float(v) for v in s * z], "redraws": attempt}
    raise RuntimeError(f"no valid truth for {spec.key} in 200 draws")


def effect_values(spec: Spec, magnitudes: dict[str, float]) -> dict[str, float]:
    """The extended (library) effect parameters of the record: the fixed shape ones and the magnitudes (of a mixed
    record, its library effect's only)."""
    from toggle_id.effects import ALL_INDEX

    if spec.outside == "saturation":  # the library's torque_constant_saturation, c_kt = 1/i_sat²
        return {"c_kt": float(magnitudes["i_sat"]) ** -2}
    if not spec.effects:
        return {}
    return {**spec.fixed, **{k: float(magnitudes[k]) for k in spec.calibrate if k in ALL_INDEX and k in magnitudes}}


#: The independent plant's term of each outside effect: (its magnitude's name, its Outside keyword and value).
_OUTSIDE_TERMS = {"bump": ("F_b", lambda m: {"bump": (m, BUMP_AT, BUMP_WIDTH)}),
                  "saturation": ("i_sat", lambda m: {"i_sat": m}), "drag": ("c_q", lambda m: {"drag": m}),
                  "scale": ("a_s", lambda m: {"scale": (m, SCALE_PITCH, SCALE_PHASE)}),
                  "pin_friction": ("pin_mu", lambda m: {"pin_mu": m}),
                  "scale_factor": ("e_s", lambda m: {"scale_factor": m}),
                  "deadband": ("v_db", lambda m: {"deadband": m}),
                  "kt_drift": ("d_kt", lambda m: {"kt_drift": (m, DURATION)}),
                  "compliance": ("c_k", lambda m: {"compliance": (1.0 / m, COMPLIANCE_ZETA)}),
                  "hc_damping": ("l_hc", lambda m: {"hc_damping": m})}


def outside_of(spec: Spec, magnitudes: dict[str, float]):
    """The independent plant's effects of ``spec`` at ``magnitudes`` (those absent are off: a mixed record's
    calibration switches on one effect at a time); a mixed record's library cogging torque is the plant's own."""
    from outside_plant import Outside

    kw: dict = {}
    if spec.outside:
        param, term = _OUTSIDE_TERMS[spec.outside]
        if param in magnitudes:
            kw.update(term(float(magnitudes[param])))
    if spec.category == "mixed":
        lib = effect_values(spec, magnitudes)
        if "a_cog" in lib:
            kw["cogging"] = (lib["a_cog"], lib["n_cog"], lib["phi_cog"])
    return Outside(**kw)


def clean_response(spec: Spec, theta: np.ndarray, effects: dict, magnitudes: dict, rec) -> tuple[np.ndarray, np.ndarray]:
    """Noiseless x_B and i_q of the truth on ``rec``: the project's simulator for library effects, the independent
    plant for effects outside the library."""
    if spec.outside:
        from outside_plant import simulate_outside

        x, i, info = simulate_outside(theta, rec, outside_of(spec, magnitudes))
        if info["status"]:
            raise RuntimeError(f"{spec.key}: the outside plant failed ({info['message']})")
        return x, i
    from toggle_id.effects import ALL_INDEX
    from toggle_id.simulate import PRECISE, extend, simulate

    th = extend(theta)
    for k, v in effects.items():
        th[0, ALL_INDEX[k]] = v
    sim = simulate(th, rec, PRECISE)
    if sim.status[0] != 0:
        raise RuntimeError(f"{spec.key}: the truth cannot be simulated ({sim.status_counts()})")
    return sim.x_B[0], sim.i_q[0]


def noise_seed(spec: Spec) -> int:
    return 7000 + spec.seed


def disturbance_seed(spec: Spec, seed: int) -> int:
    """The seed of a record's disturbance (:func:`disturbance`) for its noise seed ``seed``: the record's own, its
    validation record's and its replicates' differ as their noise seeds do."""
    return spec.seed + 777 + (seed - noise_seed(spec))


#: Disturbances of the reading beyond the measurement model of :func:`toggle_id.record.measure` (``Spec.disturbance``).
DISTURBANCES = ("tone", "ar2", "walk")
#: The resonant AR(2) disturbance's pole radius and frequency (Hz, at 1 kHz sampling).
AR2_RADIUS, AR2_HZ = 0.97, 20.0


def disturbance(kind: str, t: np.ndarray, seed: int) -> np.ndarray:
    """The disturbance ``kind`` of the reading at the sample times ``t`` (m), from ``default_rng(seed)``:

    * ``tone``: white noise of 1 µm and a 50-Hz tone of 1 µm amplitude at a random phase (mains pickup);
    * ``ar2``: resonant AR(2) noise, poles at radius 0.97 and 20 Hz (at 1 kHz sampling; a mounting's resonance
      excited by vibration), 2000 samples of burn-in, scaled to a standard deviation of 1 µm;
    * ``walk``: white noise of 1 µm and a random walk of the reading, its steps scaled so that its standard
      deviation at the record's end is 3 µm (a reference that wanders)."""
    rng = np.random.default_rng(seed)
    n = np.size(t)
    if kind == "tone":
        return 1e-6 * rng.standard_normal(n) + 1e-6 * np.sin(2 * np.pi * 50.0 * np.asarray(t, float)
                                                              + rng.uniform(0, 2 * np.pi))
    if kind == "ar2":
        r, th = AR2_RADIUS, 2 * np.pi * AR2_HZ / 1000.0
        a1, a2 = 2 * r * math.cos(th), -r * r
        w = rng.standard_normal(n + 2000)
        e = np.zeros(n + 2000)
        for k in range(2, n + 2000):
            e[k] = a1 * e[k - 1] + a2 * e[k - 2] + w[k]
        e = e[2000:]
        return e * (1e-6 / e.std())
    if kind == "walk":
        walk = np.cumsum(rng.standard_normal(n))
        walk *= 3e-6 / np.sqrt(n)
        return 1e-6 * rng.standard_normal(n) + walk
    raise ValueError(f"unknown disturbance {kind!r}: one of {', '.join(DISTURBANCES)}")


#: The validation record's command for a record's command: the other kind of motion (a swept machine is also run
#: open/close; a cycling one is also swept, with the experiment sweep's larger amplitude).
SECOND_COMMAND = {"simulation": "cycling", "experiment": "cycling", "cycling": "experiment"}
#: Offset of the validation record's noise seed: independent noise of the same model.
VALIDATION_SEED_OFFSET = 5000
#: Step of a replicate's noise seed (``--replicates``): the same machine again, with independent noise.
REPLICATE_SEED_STEP = 100_000
#: Step of a held-out draw's noise seed (``--draw``): another machine of the same spec, with independent noise.
DRAW_SEED_STEP = 10_000_000


def replicate_count(spec: Spec, replicates: int) -> int:
    """How many records ``spec`` gives with ``replicates`` asked for: itself and the replicates, or itself alone when
    it has no random noise (a quantised reading only: a replicate would be the same record; a disturbance of the
    reading is random, its replicates drawn as their noise)."""
    return replicates + 1 if spec.noise_m > 0 or spec.disturbance else 1


def replicate_name(name: str, replicate: int, draw: int = 0) -> str:
    """``rec19`` for the record itself, ``rec19_r2`` for its second replicate; ``rec19_d1`` (``rec19_d1_r2``) for
    the spec's first held-out machine (its second replicate)."""
    name = name if draw == 0 else f"{name}_d{draw}"
    return name if replicate == 0 else f"{name}_r{replicate}"


def make_record(spec: Spec, calibrated: dict[str, tuple[float, float]], duration: float = DURATION,
                validation: bool = False, replicate: int = 0, draw: int = 0):
    """(record with noisy x_B, manifest entry) of ``spec`` with its ``calibrated`` {parameter: (value, ratio)}.

    ``validation``: the second record of the same machine (truth, effects, noise model) under
    :data:`SECOND_COMMAND` with independent noise, named ``<name>_validation`` — what a user would record to check
    a model on data it was not fitted on. ``replicate`` k > 0: the same record (truth, effects, command, noise
    model) with independent noise, named ``<name>_r<k>`` — one verdict is one draw of the noise; replicates
    measure how often it comes out so (a false-alarm rate on the noise-only records). ``draw`` k > 0: the spec's
    k-th held-out machine (:func:`draw_truth`; ``calibrated`` must then be its own), named ``<name>_d<k>``."""
    from toggle_id.app.records import build_record
    from toggle_id.effects import EFFECTS_BY_NAME
    from toggle_id.params import PARAM_NAMES
    from toggle_id.record import measure

    magnitudes = {k: float(v[0]) for k, v in calibrated.items()}
    theta, drawn = draw_truth(spec, draw)
    effects = effect_values(spec, magnitudes)
    if replicate < 0:
        raise ValueError(f"replicate must be >= 0, got {replicate}")
    name = replicate_name(NAMES[spec.key], replicate, draw) + ("_validation" if validation else "")
    kind = SECOND_COMMAND[spec.command] if validation else spec.command
    seed = (noise_seed(spec) + (VALIDATION_SEED_OFFSET if validation else 0) + REPLICATE_SEED_STEP * replicate
            + DRAW_SEED_STEP * draw)
    if spec.outside:
        rec = base_record(kind, duration)
        x, i = clean_response(spec, theta, effects, magnitudes, rec)
        rec.x_B = measure(x, **spec.noise, seed=seed)
        rec.i_q = i
        simulator = "tests/outside_plant.py (scipy DOP853, rtol 1e-11)"
    else:
        data = {"source": "simulated", "command": "cycling" if kind == "cycling" else "sweep",
                "sweep": kind if kind != "cycling" else "simulation", "duration": duration,
                "params": dict(zip(PARAM_NAMES, map(float, theta))), "effects": effects, **spec.noise,
                "noise_seed": seed}
        rec, _ = build_record(data)
        simulator = "toggle_id.simulate (PRECISE)"
    disturbed = {}
    if spec.disturbance:  # beyond the measurement model, drawn apart from it
        d_seed = disturbance_seed(spec, seed)
        e = disturbance(spec.disturbance, rec.t, d_seed)
        rec.x_B = rec.x_B + e
        disturbed = {"disturbance": spec.disturbance, "disturbance_seed": d_seed,
                     "effective_sigma_m": float(np.sqrt(np.mean(e ** 2)))}
    rec.name = name
    from toggle_id.record import CYCLING, SWEEPS

    command = (CYCLING.to_dict() if kind == "cycling" else
               {"kind": "sweep", "sweep": kind, **SWEEPS[kind].__dict__})
    entry = {
        "name": name, "file": f"{name}.csv", "key": spec.key, "category": spec.category, "replicate": replicate,
        "draw": draw,
        "effects": list(spec.effects),
        "effect_params": {e: {p.name: effects.get(p.name, p.off) for p in EFFECTS_BY_NAME[e].params}
                          for e in spec.effects},
        "outside": ({k: v for k, v in outside_of(spec, magnitudes).to_dict().items() if k not in spec.effects}
                    if spec.outside else {}),
        "params": dict(zip(PARAM_NAMES, map(float, theta))), "perturbation": drawn,
        "noise": {"model": "none" if spec.noise_m == 0 else ("ar1" if spec.noise_ar else "white"),
                  "sigma_m": spec.noise_m, "ar": spec.noise_ar, "quantum_m": spec.quantum_m,
                  **({"outlier_fraction": spec.outlier_fraction, "outlier_m": spec.outlier_m}
                     if spec.outlier_fraction else {}),
                  "seed": seed, "effective_sigma_m": spec.sigma_eff, **disturbed},
        "command": command, "duration_s": duration, "samples": rec.n, "simulator": simulator,
        "calibration": ({"target_ratio": ({k: spec.target_of(k) for k in spec.calibrate} if spec.targets
                                          else spec.target), "magnitudes": magnitudes,
                         "measured_ratio": {k: float(v[1]) for k, v in calibrated.items()},
                         **({"combined_ratio": COMBINED_RATIO[spec.key]} if spec.key in COMBINED_RATIO else {}),
                         "valid_for_duration_s": DURATION} if spec.calibrate else None),
    }
    if not spec.outside:
        over = [f"params.{k}={v!r}" for k, v in entry["params"].items()]
        over += [f"effects.{k}={v!r}" for k, v in effects.items()]
        entry["jobs_simulate"] = " ".join(
            ["python -m jobs.simulate", f"out={name}.csv", f"command={data['command']}", f"sweep={data['sweep']}",
             f"duration={duration}", f"noise_m={spec.noise_m}", f"noise_ar={spec.noise_ar}",
             f"quantum_m={spec.quantum_m}",
             *([f"outlier_fraction={spec.outlier_fraction}", f"outlier_m={spec.outlier_m}"]
               if spec.outlier_fraction else []), f"seed={seed}", *over])
    return rec, entry


# ------------------------------------------------------------------------------------------ generation
def select(only: str | None) -> list[Spec]:
    """The specs named in ``only`` (public names or keys, comma-separated; None: all)."""
    if not only:
        return list(SPECS)
    out = []
    for item in (s.strip() for s in only.split(",") if s.strip()):
        key = KEYS_BY_NAME.get(item, item)
        if key not in SPECS_BY_KEY:
            raise SystemExit(f"error: unknown record {item!r}; known: {', '.join(sorted(NAMES.values()))} "
                             f"or {', '.join(SPECS_BY_KEY)}")
        out.append(SPECS_BY_KEY[key])
    return out


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def generate(out: Path, specs: list[Spec], calibrated: dict[str, dict[str, tuple[float, float]]],
             duration: float = DURATION, log=print, validation: bool = False, replicates: int = 0,
             draw: int = 0) -> dict:
    """Write the records of ``specs`` and the manifest (merged with an existing one); return the manifest.
    ``validation``: also each record's second record (:func:`make_record`), named in its entry's ``validation``;
    ``replicates``: also that many replicates of each record (independent noise, ``<name>_r1`` …); ``draw`` k > 0:
    the specs' k-th held-out machines instead (``calibrated`` for them)."""
    from toggle_id.checkpoint import atomic_write_json
    from toggle_id.data import write_csv

    out.mkdir(parents=True, exist_ok=True)
    path = out / "manifest.json"
    manifest = json.loads(path.read_text()) if path.exists() else {}
    records = {r["name"]: r for r in manifest.get("records", [])}
    for spec in specs:
        if spec.calibrate and set(calibrated.get(spec.key, {})) != set(spec.calibrate):
            raise SystemExit(f"error: {spec.key} has no calibrated magnitude; run with --calibrate")
        if replicates and replicate_count(spec, replicates) == 1:  # nothing random to draw again
            log(f"{NAMES[spec.key]}: no random noise (a quantised reading only), so no replicates: each would be "
                "the same record")
        for k in range(replicate_count(spec, replicates)):
            t0 = time.perf_counter()
            rec, entry = make_record(spec, calibrated.get(spec.key, {}), duration, replicate=k, draw=draw)
            csv = write_csv(rec, out / entry["file"])
            entry["sha256"] = sha256(csv)
            if validation:
                vrec, ventry = make_record(spec, calibrated.get(spec.key, {}), duration, validation=True, replicate=k,
                                           draw=draw)
                vcsv = write_csv(vrec, out / ventry["file"])
                entry["validation"] = {"file": ventry["file"], "command": ventry["command"],
                                       "noise_seed": ventry["noise"]["seed"], "sha256": sha256(vcsv)}
            records[entry["name"]] = entry
            log(f"{entry['name']}: {rec.n} samples ({time.perf_counter() - t0:.1f} s)")
    manifest = {"generated_by": "python -m jobs.bench_adversarial", "sigma_m": SIGMA,
                "calibrated_for_duration_s": DURATION,
                "note": "record names say nothing about their content; this manifest is the truth",
                "records": [records[k] for k in sorted(records)]}
    atomic_write_json(path, manifest)
    return manifest
