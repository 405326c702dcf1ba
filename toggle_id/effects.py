"""Candidate effects the nominal model lacks (issue: close the loop). Placeholder layout; see _kernels."""
from __future__ import annotations

import numpy as np

from . import _kernels as K

EXTRA_NAMES = ("tau_c", "F_s", "v_s", "c_B", "tau_d", "b_l", "a_cog", "n_cog", "phi_cog", "F_load", "k3", "s_sat", "x_off")
EXTRA_DEFAULTS = np.zeros(K.N_THETA - 15)
EXTRA_DEFAULTS[K.V_S - 15] = 0.01
EXTRA_DEFAULTS[K.N_COG - 15] = 1.0
