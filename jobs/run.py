"""`python -m jobs.run [+experiment=NAME] [key=value ...]`: the identification workflow (Hydra entry point).

Experiments: one_stage, two_stage (default method), table1, discover, emps, excite (propose the input that tells
rival explanations apart, toggle_id/excite/). Multirun sweeps work:
`python -m jobs.run -m +experiment=two_stage ga.population=200,1000 seed=0,1,2`.
The last line of output is `report: <absolute path of the job's report>`.
"""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_original_cwd
from omegaconf import DictConfig, OmegaConf

from jobs._cli import guarded, precheck

#: Job name (the config's ``job`` key) -> the application function that runs it (module, name in toggle_id/app/),
#: imported only when that job runs: a bad command line is reported before the library loads.
JOBS = {
    "identify": ("toggle_id.app.identify", "run_identify"),
    "table1": ("toggle_id.app.table1", "run_table1"),
    "discover": ("toggle_id.app.discover", "run_discover"),
    "emps": ("toggle_id.app.emps", "run_emps"),
    "identifiability": ("toggle_id.app.study", "run_study"),
    "excite": ("toggle_id.app.excite", "run_excite"),
}


def run(cfg: dict, run_dir: str, project_root: str) -> str:
    """Dispatch a composed, resolved configuration to its job; return the report path."""
    job = cfg.get("job", "identify")
    if job not in JOBS:
        from toggle_id.errors import ConfigError

        raise ConfigError(f"unknown job {job!r}; known: {', '.join(JOBS)}")
    module, function = JOBS[job]
    return str(getattr(importlib.import_module(module), function)(cfg, run_dir, project_root))


def tracking_context(hc, project_root: str) -> tuple[list[str], dict]:
    """What the MLflow run of this job is named after and tagged with: Hydra's task overrides (the job's
    command-line differences, e.g. ``ga.population=200 seed=1``) and, in a multirun, the sweep (its directory,
    absolute, and the job's number in it)."""
    from hydra.types import RunMode

    overrides = list(hc.overrides.task)
    tags = {}
    if hc.mode == RunMode.MULTIRUN:
        sweep = Path(hc.sweep.dir)
        tags = {"sweep": str(sweep if sweep.is_absolute() else Path(project_root) / sweep),
                "sweep.job": str(hc.job.num)}
    return overrides, tags


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from toggle_id.tracking import run_context

    plain = OmegaConf.to_container(cfg, resolve=True)
    hc = HydraConfig.get()
    run_dir = hc.runtime.output_dir
    overrides, tags = tracking_context(hc, get_original_cwd())
    with run_context(overrides, tags):
        report = guarded(lambda: run(plain, run_dir, get_original_cwd()))
    print(f"report: {report}", flush=True)


if __name__ == "__main__":
    precheck("config", sys.argv[1:])
    main()
