"""What a checkpoint of a GA identification holds: the GA state of the running stage (every ``every``
generations) and the stages already finished, as dictionaries (:func:`stage_to_dict`, read back by
:func:`stage_from_dict`); files written atomically by :mod:`toggle_id.checkpoint` (JSON + npz, no pickle).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .checkpoint import load_checkpoint, save_checkpoint
from .errors import CheckpointError, ConfigError
from .ga import RGA, join_state, split_state
from .results import StageResult


class Checkpointer:
    """GA state (population, fitness, RNG, generation, best, stage) saved every ``every`` generations, with the
    results of the stages already finished; written atomically (JSON + npz, no pickle)."""

    def __init__(self, directory: str | Path, every: int = 5, meta: Mapping[str, Any] | None = None) -> None:
        if int(every) < 1:
            raise ConfigError(f"checkpoint.every must be >= 1, got {every}")
        self.prefix = Path(directory) / "checkpoint"
        self.every = int(every)
        self.meta = dict(meta or {})  # saved along (e.g. the job's identity, toggle_id.jobdir)

    def exists(self) -> bool:
        return self.prefix.with_suffix(".json").exists()

    def save(self, stage: str, ga: RGA, done: list[dict]) -> None:
        arrays, meta = split_state(ga.state_dict())
        save_checkpoint(self.prefix, arrays, {**self.meta, "stage": stage, "ga": meta, "done": done})

    def load(self) -> tuple[str, dict, list[dict]]:
        arrays, meta = load_checkpoint(self.prefix)
        try:
            return str(meta["stage"]), join_state(arrays, meta["ga"]), list(meta["done"])
        except (KeyError, TypeError) as err:
            raise CheckpointError(f"checkpoint {self.prefix} lacks {err}") from err


def stage_to_dict(st: StageResult) -> dict:
    """A finished stage as a checkpoint keeps it: its report dictionary plus ``theta`` and ``x``."""
    d = st.to_dict()
    d["theta"] = [float(v) for v in st.theta]
    d["x"] = [float(v) for v in st.x]
    return d


def stage_from_dict(d: dict, theta: np.ndarray) -> StageResult:
    """The finished stage back from :func:`stage_to_dict`'s dictionary (``theta`` is not used)."""
    return StageResult(name=d["name"], free=tuple(d["free"]), x=np.array(d["x"]), theta=np.array(d["theta"]),
                       window=tuple(d["window"]), fitness_ga=d["fitness_ga"], fitness=d["fitness"], sse=d["sse_m2"],
                       history=list(d["fitness_history"]), generations=d["generations"],
                       converged_generation=d["converged_generation"], n_evaluations=d["n_evaluations"],
                       seconds_ga=d["seconds_ga"], seconds_polish=d["seconds_polish"], polish=d.get("polish"),
                       identifiability=d.get("identifiability"),
                       windows=None if d.get("windows") is None else tuple(tuple(w) for w in d["windows"]),
                       n_simulations=int(d.get("n_simulations", d["n_evaluations"])))
