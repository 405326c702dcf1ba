"""EMPS (electro-mechanical positioning system) benchmark: the library's second plant, with real measured data.

- :mod:`.data`: :class:`EmpsRecord`, :func:`load_emps_csv`, :func:`load_emps_mat`, and
  :func:`find_benchmark_files` (the benchmark's records where a user has them, checked by sha256);
- :mod:`.model`: parameters, the effect registry :data:`EFFECTS`, the batched numba closed-loop simulator
  :func:`simulate_emps` (kernel :func:`simulate_kernel`);
- :mod:`.idim`: the benchmark's IDIM-LS recipe :func:`idim_ls`;
- :mod:`.fit`: output-error residual/Jacobian/fit, the judge of an effect :func:`judge_effect` (into the discovery
  engine's ``Evidence``) and the prediction of a held-out record :func:`predict_validation`;
- :mod:`.loop`: the greedy effect-discovery loop :func:`run_emps_loop` with the discovery engine's verdict rules
  (the three lists :func:`three_lists`; the structure test of the final residual :func:`localise`).

The names below are imported on first use, so that finding and checking the records (:mod:`.data`) does not wait
for numba.
"""
from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, tuple[str, ...]] = {
    "data": ("CITATION", "ENV_DIR", "ESTIMATION_FILE", "GTAU", "KP", "KV", "SHA256", "VALIDATION_FILE",
             "BenchmarkFiles", "EmpsRecord", "EmpsRecordsNotFound", "find_benchmark_files", "load_emps_csv",
             "load_emps_mat", "loader_cache_dir"),
    "fit": ("OEFitResult", "fit_output_error", "judge_effect", "make_jacobian", "make_residual",
            "predict_validation"),
    "loop": ("localisation_signals", "localise", "run_emps_loop", "three_lists"),
    "idim": ("idim_ls",),
    "model": ("EFFECTS", "NOMINAL_NAMES", "PARAM_NAMES", "PUBLISHED", "PUBLISHED_THETA", "Effect", "EmpsSimResult",
              "controller_law", "position_rel_error_pct", "simulate_emps", "simulate_kernel", "theta_from_dict",
              "theta_to_dict"),
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}
__all__ = [name for names in _EXPORTS.values() for name in names]


def __getattr__(name: str) -> Any:
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{mod}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
