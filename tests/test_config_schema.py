"""Typed config nodes (jobs/schema.py): every default has one home, the library dataclass, and a misspelt key or a
value of the wrong type stops the job in one line before any work."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from jobs import _cli
from jobs.schema import SCHEMAS

CONF = Path(_cli.CONF_DIR)
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
CASES = [[]] + [[f"+experiment={name}"] for name in EXPERIMENTS]

#: a composition that has each typed node
WHERE = {"ga": [], "polish": [], "fast": [], "solver": [], "excite": ["+experiment=excite"],
         "emps": ["+experiment=emps"], "discover": ["+experiment=discover"]}
#: a key of each typed node and a value of the wrong type for it
WRONG_TYPE = {"ga": "population=abc", "polish": "max_nfev=1.5", "fast": "keep=half", "solver": "ga_tier=[1]",
              "excite": "v_max=big", "emps": "samples=many", "discover": "alpha=low"}


def _compose(overrides: list[str]) -> dict:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=False)


def _defaults(cls: type) -> dict:
    """A dataclass's defaults as plain config values (tuples as lists, nested dataclasses as dicts)."""
    return OmegaConf.to_container(OmegaConf.create(dataclasses.asdict(cls())))


def _load(path: Path) -> dict:
    """A YAML file of conf/ as written (OmegaConf's reading of numbers such as 1e-4)."""
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}


def _precheck_error(capsys, overrides: list[str]) -> str:
    with pytest.raises(SystemExit) as stop:
        _cli.precheck("config", overrides)
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert stop.value.code == 2 and len(lines) == 1, lines
    return lines[0]


def test_every_node_in_where_is_a_schema():
    assert set(WHERE) == set(SCHEMAS) == set(WRONG_TYPE)


@pytest.mark.parametrize("overrides", CASES, ids=lambda ov: ov[0] if ov else "default")
def test_typed_nodes_carry_the_dataclass_defaults_where_the_yaml_is_silent(overrides):
    """Each typed node a job receives is its dataclass's defaults with only what the YAML files change."""
    cfg = _compose(overrides)
    for node, cls in SCHEMAS.items():
        if node not in cfg:
            continue
        defaults = _defaults(cls)
        assert set(cfg[node]) == set(defaults), node
        changed = {k for k in defaults if cfg[node][k] != defaults[k]}
        assert changed <= _set_by_yaml(node, overrides), (node, changed)


def _set_by_yaml(node: str, overrides: list[str]) -> set[str]:
    """The keys of ``node`` that the files of this composition give (config.yaml, the GA choice, the experiment)."""
    files = [CONF / "config.yaml", CONF / "ga" / "paper.yaml", *(CONF / "experiment" / f"{o.split('=')[1]}.yaml"
                                                               for o in overrides)]
    keys: set[str] = set()
    for path in files:
        doc = _load(path)
        keys |= set((doc if path.parent.name == node else doc.get(node)) or {})
    return keys


@pytest.mark.parametrize("node", sorted(SCHEMAS))
def test_the_stored_schema_is_the_library_dataclass(node):
    """The schema Hydra composes from is the dataclass itself: its defaults are the library's, no copy to drift."""
    from hydra.core.config_store import ConfigStore

    stored = ConfigStore.instance().load(f"schema/{node}.yaml").node
    assert OmegaConf.get_type(stored) is SCHEMAS[node]
    assert OmegaConf.to_container(stored) == _defaults(SCHEMAS[node])
    assert _compose(WHERE[node])[node] == {**_defaults(SCHEMAS[node]), **_given(node, WHERE[node])}


def _given(node: str, overrides: list[str]) -> dict:
    cfg = _compose(overrides)
    return {k: v for k, v in cfg[node].items() if k in _set_by_yaml(node, overrides)}


def _leaves(obj, prefix: str = ""):
    if isinstance(obj, dict) and obj:
        for k, v in obj.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    else:
        yield prefix, obj


def test_no_yaml_file_repeats_a_dataclass_default():
    """A YAML file gives a typed node's key only to change it: a value equal to the dataclass default is a second
    home that could drift from the first."""
    repeats = []
    for path in sorted(CONF.rglob("*.yaml")):
        doc = _load(path)
        nodes = {path.parent.name: doc} if path.parent.name in SCHEMAS else {n: doc.get(n) for n in SCHEMAS}
        for node, given in nodes.items():
            if not isinstance(given, dict):
                continue
            defaults = _defaults(SCHEMAS[node])
            for key, value in _leaves({k: v for k, v in given.items() if k != "defaults"}):
                default = defaults
                for part in key.split("."):
                    default = default.get(part, object()) if isinstance(default, dict) else object()
                if value == default:
                    repeats.append(f"{path.relative_to(CONF)}: {node}.{key} = {value!r}")
    assert not repeats, "these repeat their dataclass default (its one home): " + "; ".join(repeats)


@pytest.mark.parametrize("node", sorted(SCHEMAS))
def test_a_misspelt_key_is_one_line_naming_it(capsys, node):
    line = _precheck_error(capsys, [*WHERE[node], f"{node}.no_such_setting=1"])
    assert line.startswith("error: bad configuration") and "no_such_setting" in line


@pytest.mark.parametrize("node", sorted(SCHEMAS))
def test_a_wrong_type_is_one_line_naming_the_key(capsys, node):
    override = f"{node}.{WRONG_TYPE[node]}"
    line = _precheck_error(capsys, [*WHERE[node], override])
    assert line.startswith("error: bad configuration") and override.split("=")[0] in line


def test_a_wrong_type_on_the_command_line_stops_before_any_work(tmp_path):
    from conftest import one_line_error, run_job

    proc = run_job("jobs.run", "ga.population=abc", "tracking.enabled=false", cwd=tmp_path, timeout=120)
    line = one_line_error(proc)
    assert proc.returncode == 2 and "ga.population" in line and "abc" in line
    assert not any(tmp_path.iterdir())  # no run directory, no MLflow store: nothing started
