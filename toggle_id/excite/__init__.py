"""Propose the experiment that tells the explanations apart (issue 16).

A record often cannot decide between rival explanations: an effect the nominal parameters absorb (a motor
Coulomb torque taken up by the slider friction μ), or parameter directions the x_B sensitivities do not resolve.
This package searches an input within the machine's limits that separates them:

- :mod:`.inputs`: input families (swept sines, open/close cycling, multisines, steps), each a small
  parametrisation of the unit cube, and the check that an input drives slider B into the clamp and back;
- :mod:`.score`: the separation of two rivals that survives refitting, and the resolved singular values;
- :mod:`.rivals`: the rivals of a record (configured effects, a discovery result);
- :mod:`.search`: the seeded random search with local refinement, and the refits that verify the best.

The job ``python -m jobs.run +experiment=excite`` (``excitation.csv``, ``excite.json``, ``excite.png``) is
:func:`toggle_id.app.excite.run_excite`.
"""
from __future__ import annotations

from .inputs import FAMILY_PARAMS, Candidate, candidate_record, clamp_check, input_signal
from .rivals import build_rivals, effect_rival, specs_from_discovery
from .score import Rival, linear_separation, refit_separation, spectrum
from .search import Evaluation, Scorer, search, verify_best
from .settings import ExciteSettings, RivalSpec

__all__ = ["Candidate", "Evaluation", "ExciteSettings", "FAMILY_PARAMS", "Rival", "RivalSpec", "Scorer",
           "build_rivals", "candidate_record", "clamp_check", "effect_rival", "input_signal", "linear_separation",
           "refit_separation", "search", "specs_from_discovery", "spectrum", "verify_best"]
