"""Model discovery: find what the model lacks, add it, and say how sure we are."""
from __future__ import annotations

from .job import discover_settings, run_discover
from .loop import discover
from .model import Fit, Model, Projector, fit_free, sensitivities
from .report import DiscoveryResult
from .scoring import _magnitude_grid, score_candidates
from .settings import DiscoverSettings
from .stats import f_test

__all__ = ["DiscoverSettings", "DiscoveryResult", "Fit", "Model", "Projector", "discover", "discover_settings",
           "f_test", "fit_free", "run_discover", "score_candidates", "sensitivities", "_magnitude_grid"]
