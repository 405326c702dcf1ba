"""The EMPS job: identify the electro-mechanical positioning system benchmark from its measured record.

``python -m jobs.run +experiment=emps`` composes ``conf/experiment/emps.yaml`` and calls :func:`run_emps` with the
plain configuration. The job validates its settings, finds the benchmark's records where the user has them
(``emps.data_dir``, else ``$TOGGLE_ID_EMPS_DIR``, then the official loader's cache ``~/.nonlinear_benchmarks/EMPS/``;
each file checked by its sha256) or takes the user's own file (``emps.path``), and loads them before any work
starts. It then runs the output-error effect-discovery loop on the estimation record
(:func:`toggle_id.emps.run_emps_loop`: nominal M, Fv fit, then Coulomb friction, offset, Stribeck, asymmetry as the
data support them, each judged like the toggle plant's effects: AR noise model of the larger model's residual,
prewhitened F-test and ΔBIC, time-block cross-validation, all through the discovery engine's ``Evidence``; reported
as the toggle loop's three lists ``effects_added``, ``compensating`` and ``rejected``), tests the final model's
position residual for structure the noise model cannot explain and says where it concentrates (position, position
signed by the direction of motion, velocity; ``localisation.png``), analyses the identifiability of the final model
(:func:`toggle_id.identifiability.analyze`),
compares M, Fv, Fc and offset with the benchmark's published IDIM-LS values, predicts the validation record
(``DATA_EMPS_PULSES.mat``, its pulses entering at the controller output; nothing is fitted on it), logs everything
to MLflow (parent run ``emps``, one child run per fit), draws the figures, prints a short table and writes
``result.json`` atomically into the run directory; it returns that path. This module never imports Hydra, and it
needs neither the GA nor Ray. Its heavy imports (numba, matplotlib, MLflow) wait until the records are found.
"""
from __future__ import annotations

import math
import os
import textwrap
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..emps.data import (
    ESTIMATION_FILE,
    SHA256,
    VALIDATION_FILE,
    EmpsRecord,
    find_benchmark_file,
    find_benchmark_files,
    not_found_message,
    sha256_of,
)
from ..emps.report import (console_text, friction_figure, log_children, param_units, parent_metrics,
                           response_figure)
from ..emps.settings import EmpsSettings
from ..errors import ConfigError, DataError
from .common import get, jsonable_config, make_tracker, publish_report

#: Parameters that may be zero or negative: analysed in affine (not log) coordinates.
SIGNED_PARAMS = frozenset({"offset", "Fs", "Fc_asym", "Fv_asym"})
#: The published (IDIM-LS, symmetric model) parameters compared in the report and the console table.
COMPARED = ("M", "Fv", "Fc", "offset")
#: Keys of the ``emps`` config node and their defaults (:class:`~toggle_id.emps.settings.EmpsSettings`, their one
#: home), as a plain dict (also used when run_emps is called from Python).
EMPS_DEFAULTS: dict[str, Any] = asdict(EmpsSettings())


# ------------------------------------------------------------------------------------------ configuration
@dataclass(frozen=True)
class EmpsJobSettings:
    """Validated settings of the EMPS job (see :class:`~toggle_id.emps.settings.EmpsSettings` for the meaning of
    each)."""

    path: Path | None
    data_dir: Path | None
    validate: bool
    samples: int | None
    candidates: tuple[str, ...]
    alpha: float
    max_effects: int | None
    max_corr: float
    noise_max_order: int
    cv_block: int
    cv_folds: int
    cv_alpha: float
    bonferroni: bool
    solver: str
    max_nfev: int
    reference_fit: bool
    sim: dict = field(default_factory=dict)
    validation_path: Path | None = None
    identifiability: bool = True
    noise_std_m: float | None = None
    structure_bins: int = 12
    structure_alpha: float = 0.01
    backward: bool = True
    explain_fraction: float = 0.5
    ambiguity_alpha: float = 0.05
    glitch_k: float = 8.0


def _number(name: str, value: Any, *, integer: bool = False) -> float | int:
    """``value`` as a finite float (or int); a one-line ConfigError naming ``name`` otherwise."""
    if isinstance(value, bool) or value is None:
        raise ConfigError(f"{name} must be a {'whole ' if integer else ''}number, got {value!r}")
    try:
        num = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a {'whole ' if integer else ''}number, got {value!r}") from None
    if not math.isfinite(num):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    if integer:
        if num != int(num):
            raise ConfigError(f"{name} must be a whole number, got {value!r}")
        return int(num)
    return num


def _resolve(path: Any, project_root: str | Path, what: str) -> Path:
    """The configured file ``path`` (the setting ``what``), relative paths taken from ``project_root``."""
    if not isinstance(path, (str, Path)) or not str(path).strip() or str(path) == "???":
        raise ConfigError(f"{what} must be a file path, got {path!r}")
    p = Path(str(path)).expanduser()
    return (p if p.is_absolute() else Path(project_root) / p).resolve()


def emps_settings(cfg: Mapping, project_root: str | Path = ".") -> EmpsJobSettings:
    """Validate the ``emps``, ``validation`` and ``identifiability`` nodes; raise ConfigError (one line) on the
    first problem. Relative paths are taken relative to ``project_root`` (the directory the job was started in);
    a configured ``emps.data_dir`` must be a directory."""
    node = dict(EMPS_DEFAULTS)
    given = cfg.get("emps") or {}
    if not isinstance(given, Mapping):
        raise ConfigError(f"emps must be a mapping of settings, got {given!r}")
    unknown = sorted(set(given) - set(EMPS_DEFAULTS))
    if unknown:
        raise ConfigError(f"emps: unknown setting(s) {unknown}; known: {sorted(EMPS_DEFAULTS)}")
    node.update(given)
    sim = dict(EMPS_DEFAULTS["sim"])
    sim_given = node.get("sim") or {}
    unknown = sorted(set(sim_given) - set(sim))
    if unknown:
        raise ConfigError(f"emps.sim: unknown setting(s) {unknown}; known: {sorted(sim)}")
    sim.update(sim_given)

    path = None if node["path"] in (None, "") else _resolve(node["path"], project_root, "emps.path")
    data_dir = None if node["data_dir"] in (None, "") else _resolve(node["data_dir"], project_root, "emps.data_dir")
    if data_dir is not None and not data_dir.is_dir():
        raise ConfigError(f"emps.data_dir={data_dir} is not a directory")
    if not isinstance(node["validate"], bool):
        raise ConfigError(f"emps.validate must be true or false, got {node['validate']!r}")
    samples = node["samples"]
    if samples is not None:
        samples = _number("emps.samples", samples, integer=True)
        if samples < 10:
            raise ConfigError(f"emps.samples must be null (all) or at least 10, got {samples}")
    from ..emps.fit import SOLVERS
    from ..emps.model import EFFECTS

    cands = node["candidates"]
    if cands is None:
        cands = list(EFFECTS)
    if isinstance(cands, str) or not all(isinstance(c, str) for c in cands):
        raise ConfigError(f"emps.candidates must be a list of effect names, got {cands!r}")
    bad = [c for c in cands if c not in EFFECTS]
    if bad:
        raise ConfigError(f"emps.candidates: unknown effect(s) {bad}; known: {list(EFFECTS)}")
    if len(set(cands)) != len(cands):
        raise ConfigError(f"emps.candidates lists an effect twice: {list(cands)}")
    alpha = _number("emps.alpha", node["alpha"])
    if not 0 < alpha < 1:
        raise ConfigError(f"emps.alpha must lie in (0, 1), got {alpha}")
    max_effects = node["max_effects"]
    if max_effects is not None:
        max_effects = _number("emps.max_effects", max_effects, integer=True)
        if max_effects < 0:
            raise ConfigError(f"emps.max_effects must be null or >= 0, got {max_effects}")
    max_corr = _number("emps.max_corr", node["max_corr"])
    if not 0 < max_corr <= 1:
        raise ConfigError(f"emps.max_corr must lie in (0, 1], got {max_corr}")
    noise_max_order = _number("emps.noise_max_order", node["noise_max_order"], integer=True)
    if noise_max_order < 0:
        raise ConfigError(f"emps.noise_max_order must be >= 0 (0: white noise assumed), got {noise_max_order}")
    cv_block = _number("emps.cv_block", node["cv_block"], integer=True)
    if cv_block < 1:
        raise ConfigError(f"emps.cv_block must be >= 1 sample, got {cv_block}")
    cv_folds = _number("emps.cv_folds", node["cv_folds"], integer=True)
    if cv_folds < 2:
        raise ConfigError(f"emps.cv_folds must be >= 2, got {cv_folds}")
    if not isinstance(node["bonferroni"], bool):
        raise ConfigError(f"emps.bonferroni must be true or false, got {node['bonferroni']!r}")
    cv_alpha = _number("emps.cv_alpha", node["cv_alpha"])
    if not 0 < cv_alpha <= 0.5:
        raise ConfigError(f"emps.cv_alpha must lie in (0, 0.5], got {cv_alpha}")
    structure_bins = _number("emps.structure_bins", node["structure_bins"], integer=True)
    if structure_bins < 2:
        raise ConfigError(f"emps.structure_bins must be >= 2, got {structure_bins}")
    structure_alpha = _number("emps.structure_alpha", node["structure_alpha"])
    if not 0 < structure_alpha < 1:
        raise ConfigError(f"emps.structure_alpha must lie in (0, 1), got {structure_alpha}")
    explain_fraction = _number("emps.explain_fraction", node["explain_fraction"])
    if not 0 < explain_fraction < 1:
        raise ConfigError(f"emps.explain_fraction must lie in (0, 1), got {explain_fraction}")
    ambiguity_alpha = _number("emps.ambiguity_alpha", node["ambiguity_alpha"])
    if not 0 <= ambiguity_alpha < 1:
        raise ConfigError(f"emps.ambiguity_alpha must lie in [0, 1), got {ambiguity_alpha}")
    glitch_k = _number("emps.glitch_k", node["glitch_k"])
    if glitch_k < 0:
        raise ConfigError(f"emps.glitch_k must be >= 0 (0: no look for glitches), got {glitch_k}")
    if not isinstance(node["backward"], bool):
        raise ConfigError(f"emps.backward must be true or false, got {node['backward']!r}")
    if node["solver"] not in SOLVERS:
        raise ConfigError(f"emps.solver must be one of {list(SOLVERS)}, got {node['solver']!r}")
    max_nfev = _number("emps.max_nfev", node["max_nfev"], integer=True)
    if max_nfev < 1:
        raise ConfigError(f"emps.max_nfev must be >= 1, got {max_nfev}")
    sim_opts = {"eps": _number("emps.sim.eps", sim["eps"]), "h_lambda": _number("emps.sim.h_lambda", sim["h_lambda"]),
                "n_sub_max": _number("emps.sim.n_sub_max", sim["n_sub_max"], integer=True),
                "pulse_gain": _number("emps.sim.pulse_gain", sim["pulse_gain"])}
    if sim_opts["eps"] <= 0 or sim_opts["h_lambda"] <= 0 or sim_opts["n_sub_max"] < 2:
        raise ConfigError(f"emps.sim needs eps > 0, h_lambda > 0 and n_sub_max >= 2, got {sim_opts}")

    vpath = get(cfg, "validation.path")
    vpath = None if vpath in (None, "") else _resolve(vpath, project_root, "validation.path")
    noise = get(cfg, "identifiability.noise_std_m")
    if noise is not None:
        noise = _number("identifiability.noise_std_m", noise)
        if noise <= 0:
            raise ConfigError(f"identifiability.noise_std_m must be null or > 0, got {noise}")
    tracking = cfg.get("tracking") or {}
    if not isinstance(tracking, Mapping):
        raise ConfigError(f"tracking must be a mapping, got {tracking!r}")
    return EmpsJobSettings(path=path, data_dir=data_dir, validate=node["validate"], samples=samples, candidates=tuple(cands), alpha=alpha,
                           max_effects=max_effects, max_corr=max_corr, noise_max_order=noise_max_order,
                           cv_block=cv_block, cv_folds=cv_folds, cv_alpha=cv_alpha,
                           bonferroni=node["bonferroni"], solver=node["solver"], max_nfev=max_nfev,
                           reference_fit=bool(node["reference_fit"]), sim=sim_opts, validation_path=vpath,
                           identifiability=bool(get(cfg, "identifiability.enabled", True)), noise_std_m=noise,
                           structure_bins=structure_bins, structure_alpha=structure_alpha,
                           backward=node["backward"], explain_fraction=explain_fraction,
                           ambiguity_alpha=ambiguity_alpha, glitch_k=glitch_k)


def load_record(path: str | Path) -> EmpsRecord:
    """An EMPS record from a benchmark ``.mat`` or a ``.csv`` (t, vir, qm, qg[, pulses_N]); DataError otherwise."""
    from ..emps.data import load_emps_csv, load_emps_mat

    path = Path(path)
    if not path.is_file():
        raise DataError(f"EMPS record not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".mat":
        return load_emps_mat(path)
    if suffix == ".csv":
        return load_emps_csv(path)
    raise DataError(f"EMPS record {path.name}: unknown format {suffix!r}; expected .mat or .csv")


def _user_file(path: Path, option: str) -> dict:
    """Description of a file the user named (``emps.path`` / ``validation.path``): no hash is required, but one
    that matches a benchmark file says so."""
    if not path.is_file():
        raise DataError(f"EMPS record not found: {path} ({option})")
    digest = sha256_of(path)
    same = [name for name, h in SHA256.items() if h == digest]
    return {"file": path.name, "path": str(path), "found_in": option, "sha256": digest,
            "sha256_verified": bool(same), "benchmark_file": same[0] if same else None}


def locate_records(st: EmpsJobSettings, env: Mapping[str, str] | None = None) -> dict:
    """Where the estimation and validation records come from, before anything is loaded.

    Returns ``{"estimation": {file, path, found_in, sha256, sha256_verified, ...}, "validation": {...} or
    {"skipped": reason}}``. Without ``emps.path`` the benchmark's files are looked up
    (:func:`toggle_id.emps.data.find_benchmark_files`: a one-line DataError names the files, their source, the
    citation and where to put them when the estimation file is nowhere; a wrong sha256 is one line too). The
    validation record is ``validation.path`` when given; otherwise the benchmark's ``DATA_EMPS_PULSES.mat`` when the
    estimation record is the benchmark's (found, or ``emps.path`` with the benchmark's hash: looked for beside it
    first); ``emps.validate=false`` skips validation.
    """
    env = os.environ if env is None else env
    if st.path is None:
        files = find_benchmark_files(st.data_dir, env)
        est = files.estimation.to_dict()
        bench_val = files.validation
    else:
        est = _user_file(st.path, "emps.path")
        bench_val = None
        if est["benchmark_file"] == ESTIMATION_FILE and st.validate and st.validation_path is None:
            beside = st.path.parent / VALIDATION_FILE
            bench_val = (find_benchmark_file(VALIDATION_FILE, st.path.parent, {}) if beside.is_file()
                         else find_benchmark_file(VALIDATION_FILE, st.data_dir, env))
    if not st.validate:
        val: dict = {"skipped": "emps.validate=false"}
    elif st.validation_path is not None:
        val = _user_file(st.validation_path, "validation.path")
    elif bench_val is not None:
        val = bench_val.to_dict()
    elif st.path is None or est.get("benchmark_file") == ESTIMATION_FILE:
        val = {"skipped": not_found_message([VALIDATION_FILE], st.data_dir, env)}
    else:
        val = {"skipped": "no validation record: emps.path is the user's own record and validation.path is unset"}
    return {"estimation": est, "validation": val}


# ------------------------------------------------------------------------------------------ analysis
def _pct_diff(value: float | None, reference: float) -> float | None:
    """100·(value − reference)/|reference| (%), None when value is None."""
    return None if value is None else float(100.0 * (value - reference) / abs(reference))


def idim_reference(record: EmpsRecord) -> dict:
    """The benchmark's IDIM-LS recipe on this record (symmetric model) with % differences from the published
    values; ``{"error": ...}`` when the record is too short for it."""
    from ..emps.idim import idim_ls
    from ..emps.model import PUBLISHED

    try:
        out = idim_ls(record)
    except DataError as err:
        return {"error": str(err)}
    out["pct_diff_vs_published"] = {k: _pct_diff(out["params"][k], v) for k, v in PUBLISHED.items()}
    return out


def comparison(report: Mapping, idim: Mapping) -> dict:
    """Per compared parameter (M, Fv, Fc, offset): the published value, this record's IDIM-LS value, the final
    model's value and the output-error fit of the benchmark's own structure, each with its % difference from the
    published value (None where the model lacks the parameter, e.g. an offset absorbed by asymmetric friction)."""
    from ..emps.model import PUBLISHED

    units = param_units()
    free = set(report["free"])
    ref = (report.get("reference") or {}).get("identified") or {}
    idim_p = idim.get("params") or {}
    out = {}
    for name in COMPARED:
        pub = PUBLISHED[name]
        final = report["identified"][name] if name in free else None
        out[name] = {"unit": units[name], "published": pub,
                     "idim_ls": idim_p.get(name), "idim_ls_pct_diff": _pct_diff(idim_p.get(name), pub),
                     "final_model": final, "final_model_pct_diff": _pct_diff(final, pub),
                     "reference_fit": ref.get(name), "reference_fit_pct_diff": _pct_diff(ref.get(name), pub)}
    return out


def identifiability_of(record: EmpsRecord, theta: np.ndarray, free: list[str], sim_options: Mapping,
                       noise_std_m: float | None = None, rel_step: float = 1e-5) -> dict:
    """Local identifiability of the final model's free parameters on ``record`` (SVD of the output sensitivity).

    Positive parameters are analysed in log coordinates, the signed ones (:data:`SIGNED_PARAMS`, and any whose
    value is not > 0) in affine coordinates scaled by their magnitude. The residuals of a 1 kHz closed loop are
    strongly autocorrelated: sensitivities and residual are prewhitened by its AR noise model
    (:func:`toggle_id.discovery.noise.fit_noise`), and each variance is no smaller than the HC3 sandwich's.
    Returns the JSON form of the report plus its console ``table``; ``{"error": ...}`` if the
    analysis is impossible (e.g. a failed simulation)."""
    from ..discovery.noise import fit_noise
    from ..emps.fit import make_jacobian, make_residual
    from ..emps.model import INDEX, LOWER, UPPER
    from ..identifiability import analyze, format_table, log_jacobian

    idx = np.array([INDEX[n] for n in free])
    x = np.asarray(theta, float)[idx]
    p = len(free)
    try:
        jac = make_jacobian(record, free, theta, LOWER[idx], UPPER[idx], rel_step, sim_options)(x)
        res = make_residual(record, free, theta, sim_options)(x)
        mask = np.array([n not in SIGNED_PARAMS and v > 0 for n, v in zip(free, x)])
        jac_u = log_jacobian(jac, x, mask)
        sse = float(res @ res)
        if not (np.all(np.isfinite(jac_u)) and np.isfinite(sse)):
            raise DataError("the sensitivities of the final model are not finite")
        # The closed loop's residual is strongly autocorrelated: prewhiten by its AR noise model (the intervals of
        # the prediction-error estimate). Each variance is then the larger of the classical one and the HC3
        # sandwich's: the benchmark's residual is louder at low speed than at high (the loop's noise-level test).
        noise = fit_noise(res)
        jac_w, res_w, noise_var = noise.prewhiten(jac_u, res, None if noise_std_m is None else noise_std_m ** 2)
        rep = analyze(jac_w, res_w, free, x, n_params_fitted=p, log_mask=mask, robust=True, noise_var=noise_var)
        out = rep.to_dict()
        out.update({"sse": sse, "noise_estimated": noise_std_m is None, "noise_model": noise.to_dict()})
    except (DataError, ConfigError) as err:
        return {"error": str(err)}
    out.pop("cov_log", None)
    out["table"] = format_table(rep)
    out["note"] = (f"intervals under the residual's noise model ({noise.describe()}), each variance no smaller "
                   "than the HC3 sandwich's (a noise level that varies)")
    return out


# ------------------------------------------------------------------------------------------ the job
def run_emps(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".",
             env: Mapping[str, str] | None = None) -> Path:
    """Identify the EMPS from its record (see the module docstring); return the path of ``result.json``.

    ``cfg`` is the plain composed configuration (nodes ``emps``, ``validation``, ``identifiability``,
    ``tracking``); ``env`` (default ``os.environ``) supplies ``$TOGGLE_ID_EMPS_DIR`` and ``$HOME``. Bad settings
    raise :class:`ConfigError`, records that are missing, malformed or not the benchmark's :class:`DataError`,
    all before any fitting or tracking starts.
    """
    t0 = time.perf_counter()
    st = emps_settings(cfg, project_root)
    sources = locate_records(st, env)
    record = load_record(sources["estimation"]["path"])
    if st.samples is not None:
        if st.samples > record.n:
            raise ConfigError(f"emps.samples={st.samples} but {record.name} has only {record.n} samples")
        record = record.slice(0, st.samples)
    vsrc = sources["validation"]
    validation = None if "skipped" in vsrc else load_record(vsrc["path"])

    from .. import figures
    from ..emps.loop import run_emps_loop
    from ..emps.model import INDEX, PUBLISHED_THETA, simulate_emps, theta_from_dict

    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    tracker = make_tracker(cfg, project_root)
    with tracker.run("emps", tags={"job": "emps", "plant": "emps"}) as run:
        tracker.log_params({"emps": {**{k: v for k, v in (cfg.get("emps") or {}).items()},
                                     "record": sources["estimation"]["path"], "n_samples": record.n,
                                     "record_sha256": sources["estimation"]["sha256"]},
                            "validation.path": vsrc.get("path"),
                            "validation.sha256": vsrc.get("sha256"), "validation.skipped": vsrc.get("skipped")})
        idim = idim_reference(record)
        report = run_emps_loop(record, validation, candidates=st.candidates, alpha=st.alpha, max_nfev=st.max_nfev,
                               max_effects=st.max_effects, max_corr=st.max_corr, solver=st.solver,
                               reference_fit=st.reference_fit, noise_max_order=st.noise_max_order,
                               cv_block=st.cv_block, cv_folds=st.cv_folds, cv_alpha=st.cv_alpha,
                               bonferroni=st.bonferroni, structure_bins=st.structure_bins,
                               structure_alpha=st.structure_alpha, backward=st.backward,
                               explain_fraction=st.explain_fraction, ambiguity_alpha=st.ambiguity_alpha,
                               glitch_k=st.glitch_k, sim_options=st.sim)
        glitch = report.get("glitches") or {}
        if glitch.get("count"):  # the samples the loop left out, out of the identifiability report too
            mask = np.zeros(record.n, dtype=bool)
            mask[glitch["indices"]] = True
            record = replace(record, excluded=mask)
        final = theta_from_dict(report["identified"])
        nominal = theta_from_dict(report["nominal"]["identified"])
        report["data"] = sources
        report["idim_ls"] = idim
        report["comparison"] = comparison(report, idim)
        report["identifiability"] = (identifiability_of(record, final, report["free"], st.sim, st.noise_std_m)
                                     if st.identifiability else {"enabled": False})
        log_children(tracker, report)

        # figures: nominal, final and published models in closed loop on the record (one batched call)
        sims = simulate_emps(np.stack([nominal, final, PUBLISHED_THETA]), record, **st.sim).q
        final_label = "final: " + (" + ".join(e["name"].removesuffix("_friction") for e in report["effects_added"])
                                   or "nominal")
        fig_paths = [figures.save(response_figure(
            record, {"before (nominal M, Fv)": sims[0], final_label: sims[1], "published IDIM-LS": sims[2]},
            f"EMPS {record.name}: measured and simulated position"), run_dir / "response.png")]
        models = {"before (nominal M, Fv)": nominal, final_label: final, "published IDIM-LS": PUBLISHED_THETA}
        if report.get("reference"):
            models["OE fit of the published structure"] = theta_from_dict(report["reference"]["identified"])
        fig_paths.append(figures.save(friction_figure(record, models, float(final[INDEX["M"]]), st.sim["eps"]),
                                      run_dir / "friction.png"))
        if glitch.get("count"):  # the raw residual of the nominal model, the glitches circled
            from ..residuals import glitches_figure

            fig_paths.append(figures.save(glitches_figure(
                record.t, record.qm - sims[0], glitch["indices"],
                title=f"EMPS {record.name}: glitches of the measurement, left out of every fit and test"),
                run_dir / "glitches.png"))
        loc = report.get("localisation") or {}
        if "families" in loc:  # what the final model leaves in its position residual, and where
            from ..discovery.localise import figure as localisation_figure
            from ..emps.loop import localisation_signals

            r_final, signals = localisation_signals(record, final, st.sim)
            step = max(1, record.n // 6000)  # the dots only: the levels are the test's, from every sample
            r_final, signals = r_final[::step], {k: v[::step] for k, v in signals.items()}
            title = textwrap.fill(f"EMPS {record.name}, position residual of the final model: {loc['text']}", 140)
            fig_paths.append(figures.save(localisation_figure(loc, r_final, signals, title),
                                          run_dir / "localisation.png"))
        if validation is not None:
            vs = simulate_emps(np.stack([final, PUBLISHED_THETA]), validation, **st.sim).q
            fig_paths.append(figures.save(response_figure(
                validation, {final_label: vs[0], "published IDIM-LS": vs[1]},
                f"EMPS validation {validation.name} (predicted; fitted on {record.name} only)",
                st.sim["pulse_gain"]),
                run_dir / "validation.png"))
            report["validation"]["path"] = vsrc["path"]
            report["validation"]["sha256"] = vsrc["sha256"]
            report["validation"]["sha256_verified"] = vsrc["sha256_verified"]
        else:
            report["validation"] = {"skipped": vsrc["skipped"]}
        for p in fig_paths:
            tracker.log_artifact(p, "figures")

        report.update({"job": "emps", "plant": "emps", "path": sources["estimation"]["path"], "figures": fig_paths,
                       "mlflow_run_id": run.run_id, "config": jsonable_config(cfg),
                       "wall_seconds": time.perf_counter() - t0})
        tracker.log_metrics(parent_metrics(report))
        val = (report.get("validation") or {}).get("position_rel_error_pct")
        tracker.set_tags({"mlflow.note.content": (
            f"EMPS discovery on {record.name} ({record.n} samples): effects added "
            f"{', '.join(a['name'] for a in report['effects_added']) or 'none'}; position error "
            f"{report['position_rel_error_pct_before']:.4g} → {report['position_rel_error_pct_after']:.4g} %"
            + (f"; validation record predicted to {val:.4g} %" if val is not None else ""))})
        path = publish_report(tracker, run_dir, console_text(report), report)
    return path
