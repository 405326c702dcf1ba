"""Every Hydra config composes, experiments change what they say, and the library never imports Hydra."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import jobs.schema  # noqa: F401 — registers the typed nodes the configs name (schema/<node>)
from toggle_id.params import PARAM_NAMES

CONF = Path(__file__).resolve().parents[1] / "conf"
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


def _compose(overrides: list[str], name: str = "config"):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


def test_default_config_is_the_paper_two_stage_run():
    cfg = _compose([])
    assert cfg.job == "identify" and cfg.method == "two_stage"
    assert (cfg.ga.population, cfg.ga.generations, cfg.ga.crossover_prob, cfg.ga.mutation_prob) == (1000, 100, 0.7, 0.05)
    assert cfg.evaluator.kind == "ray" and cfg.evaluator.address is None
    assert set(cfg.data.params) == set(PARAM_NAMES)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(experiment):
    cfg = _compose([f"+experiment={experiment}"])
    plain = OmegaConf.to_container(cfg, resolve=False)
    assert plain["job"] in ("identify", "table1", "discover", "emps", "identifiability", "excite")


def test_experiments_select_their_method_and_job():
    assert _compose(["+experiment=one_stage"]).method == "one_stage"
    assert _compose(["+experiment=two_stage"]).method == "two_stage"
    assert _compose(["+experiment=table1"]).job == "table1"


@pytest.mark.parametrize("group,choice", [("evaluator", "serial"), ("ga", "small"), ("data", "csv")])
def test_config_groups_switch(group, choice):
    cfg = _compose([f"{group}={choice}"])
    if group == "evaluator":
        assert cfg.evaluator.kind == "serial"
    elif group == "ga":
        assert cfg.ga.population < 1000
    else:
        assert cfg.data.source == "csv"


def test_simulate_config_composes_with_param_overrides():
    cfg = _compose(["out=x.csv", "params.K_t=0.6", "sweep=experiment"], name="simulate")
    assert cfg.params.K_t == 0.6 and cfg.sweep == "experiment"


def test_library_never_imports_hydra():
    lib = Path(__file__).resolve().parents[1] / "toggle_id"
    for path in lib.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            assert not any(n.split(".")[0] in ("hydra", "omegaconf") for n in names), f"{path} imports {names}"
