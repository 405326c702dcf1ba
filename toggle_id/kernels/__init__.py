"""Compiled kernels of the plant (numba): its right-hand side, its Jacobian, and adaptive integrators with dense
output and exact location of the contact instant, batched over parameter vectors.

Small, pure functions on float64 arrays and scalars; failures are returned as status codes, never raised.
The readable model and the independent reference for these kernels are in :mod:`toggle_id.plant`.

Modules, each importing only those above it (no cycle; ``tests/test_architecture.py`` checks it):

- :mod:`.slots`: the layouts of the shared arrays (parameter, geometry, settings and constant slots), status codes;
- :mod:`.tableaus`: the DOPRI5 and Rodas4 coefficients;
- :mod:`.geometry`: the toggle's kinematics, closed form and Hermite table;
- :mod:`.rhs`: per-individual constants, the command, the forces with every effect term, dy/dt and its Jacobian;
- :mod:`.stepping`: what both integrators share (dense output, step-size control, event bracketing);
- :mod:`.rigid`: Rodas4 and DOPRI5 steps and the rigid plant's integrator :func:`~.rigid._simulate_one`;
- :mod:`.backlash`: the two-body integrator of the backlash effect, :func:`~.backlash.simulate_lash`;
- :mod:`.sens`: forward sensitivities of the rigid integrator's solution, by retracing its logged steps;
- :mod:`.driver`: the batched loops over rows that :mod:`toggle_id.simulate` calls.

Names with a leading underscore are compiled helpers for the other kernels (and the tests); the Python side uses
:mod:`.slots`, :func:`.geometry.build_table` and :mod:`.driver`'s ``simulate_batch_serial`` /
``simulate_batch_parallel``. This package imports nothing else of :mod:`toggle_id`.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np


def kernel_array(a, dtype=np.float64) -> np.ndarray:
    """``a`` as the one array type the kernels are compiled for: C-contiguous, writeable, ``dtype`` (copied only
    when it is not). Ray hands its workers read-only arrays; numba types those as another signature and would
    compile every kernel again in each worker (minutes on a cold cache)."""
    return np.require(a, dtype=dtype, requirements=("C", "W"))


def _drop_stale_caches(here: Path | None = None) -> None:
    """Numba's ``cache=True`` checks only the timestamp of the file that defines a function, but these kernels
    inline functions of the other files of the package (``rhs._motor_force`` into ``rigid._simulate_one``…): after
    an edit of ``rhs.py`` a cached integrator would still run the old term. So the package keeps a digest of all
    its sources beside numba's in-tree cache and empties that cache when the digest changes. A read-only install
    (numba then caches elsewhere, per user) is left alone. ``here``: the package directory (tests)."""
    here = Path(__file__).resolve().parent if here is None else Path(here)
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sorted(here.glob("*.py")))).hexdigest()
    cache = here / "__pycache__"
    stamp = cache / "kernels-sources.sha256"
    try:
        if stamp.read_text() == digest:
            return
    except OSError:
        pass
    try:
        cache.mkdir(exist_ok=True)
        for f in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
            f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass


_drop_stale_caches()
