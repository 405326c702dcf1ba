"""Typed configuration nodes: the library's settings dataclasses registered as Hydra structured-config schemas.

A dataclass of the library is the one home of its node's defaults (the numbers and what they mean); the YAML files
in ``conf/`` name the schema in their defaults list (``- schema/ga@ga``) and give only what a job or an experiment
changes. Composing a configuration checks every typed node against its dataclass, so a misspelt key or a value
of the wrong type (``ga.population=abc``) is refused before any work, in one line (``jobs/_cli.py: precheck``).
The library itself never sees Hydra: the jobs still receive plain dicts.

:data:`SCHEMAS` maps each node to its dataclass; :func:`register` stores them in Hydra's ``ConfigStore`` as
``schema/<node>``. Importing this module registers them (``jobs/_cli.py`` does, so every entry point has them).
"""
from __future__ import annotations

from hydra.core.config_store import ConfigStore

from toggle_id.discovery.settings import DiscoverJobSettings
from toggle_id.emps.settings import EmpsSettings
from toggle_id.excite.settings import ExciteSettings
from toggle_id.fast import FastSettings
from toggle_id.ga import GAConfig
from toggle_id.simulate import SolverChoice
from toggle_id.stages import PolishSettings

#: config node -> the library dataclass that is its schema and the home of its defaults
SCHEMAS: dict[str, type] = {
    "ga": GAConfig,
    "polish": PolishSettings,
    "fast": FastSettings,
    "solver": SolverChoice,
    "excite": ExciteSettings,
    "emps": EmpsSettings,
    "discover": DiscoverJobSettings,
}


def register() -> None:
    """Store every schema as ``schema/<node>`` in Hydra's ConfigStore (idempotent)."""
    cs = ConfigStore.instance()
    for node, cls in SCHEMAS.items():
        cs.store(group="schema", name=node, node=cls)


register()
