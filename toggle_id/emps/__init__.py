"""EMPS (electro-mechanical positioning system) benchmark: the library's second plant, with real measured data.

- :mod:`.data`: :class:`EmpsRecord`, :func:`load_emps_csv`, :func:`load_emps_mat`;
- :mod:`.model`: parameters, the effect registry :data:`EFFECTS`, the batched numba closed-loop simulator
  :func:`simulate_emps` (kernel :func:`simulate_kernel`);
- :mod:`.idim`: the benchmark's IDIM-LS recipe :func:`idim_ls`;
- :mod:`.fit`: output-error residual/Jacobian/fit and the greedy effect-discovery loop :func:`run_emps_loop`.
"""
from .data import DEFAULT_CSV, DEFAULT_MAT, GTAU, KP, KV, EmpsRecord, load_emps_csv, load_emps_mat
from .fit import OEFitResult, fit_output_error, make_jacobian, make_residual, run_emps_loop
from .idim import idim_ls
from .model import (EFFECTS, NOMINAL_NAMES, PARAM_NAMES, PUBLISHED, PUBLISHED_THETA, Effect, EmpsSimResult,
                    controller_law, position_rel_error_pct, simulate_emps, simulate_kernel, theta_from_dict,
                    theta_to_dict)

__all__ = [
    "DEFAULT_CSV", "DEFAULT_MAT", "GTAU", "KP", "KV", "EmpsRecord", "load_emps_csv", "load_emps_mat",
    "OEFitResult", "fit_output_error", "make_jacobian", "make_residual", "run_emps_loop", "idim_ls",
    "EFFECTS", "NOMINAL_NAMES", "PARAM_NAMES", "PUBLISHED", "PUBLISHED_THETA", "Effect", "EmpsSimResult",
    "controller_law", "position_rel_error_pct", "simulate_emps", "simulate_kernel", "theta_from_dict", "theta_to_dict",
]
