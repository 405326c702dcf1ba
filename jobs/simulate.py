"""`python -m jobs.simulate out=FILE.csv [command=sweep|cycling] [sweep=simulation|experiment] [params.NAME=VALUE ...]
[effects.NAME=VALUE ...] [noise_m=SIGMA] [noise_ar=RHO] [quantum_m=Q]
[outlier_fraction=F outlier_m=S] [seed=N] [input.path=INPUT.csv]`

Simulates the plant (PRECISE tier) and writes a record in the CSV format of docs/model.md §8 (t, v_in, x_B, i_q):
the paper's swept sine or the open/close cycling command (``command=cycling``), x_B with white or AR(1)
Gaussian noise (``noise_ar``), gross errors on a fraction of the samples (``outlier_fraction``,
``outlier_m``) and optionally quantised to an encoder's resolution (``quantum_m``).
``input.path=INPUT.csv`` simulates under any given input instead: a CSV with columns ``t`` (s) and ``v_in`` (V),
uniformly sampled at ``rate_hz``, |v_in| ≤ ``input.v_max``, at most ``input.max_duration`` s (e.g. the
``excitation.csv`` of ``+experiment=excite``); a bad file is one line on stderr and exit status 2. The last line
of output is `report: <absolute path of the CSV>`.
"""
from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.utils import get_original_cwd
from omegaconf import DictConfig, OmegaConf

from jobs._cli import guarded, precheck


def write_record(cfg: dict, cwd: str) -> Path:
    from toggle_id.app.records import build_record
    from toggle_id.data import write_csv
    from toggle_id.errors import ConfigError

    out = cfg.get("out")
    if not out or out == "???":
        raise ConfigError("out must name the CSV file to write (out=FILE.csv)")
    keys = ("command", "sweep", "duration", "rate_hz", "params", "effects", "noise_m", "noise_ar", "quantum_m",
            "outlier_fraction", "outlier_m", "x_B0")
    data = {k: cfg[k] for k in keys if k in cfg}
    data.update(source="simulated", noise_seed=cfg.get("seed", 0))
    try:
        duration = float(data.get("duration", 5.0))
    except (TypeError, ValueError):
        duration = float("nan")
    if not duration > 0:
        raise ConfigError(f"duration must be a positive time in seconds, got {data.get('duration')}")
    path = Path(out).expanduser()
    if not path.is_absolute():
        path = Path(cwd) / path
    inp = cfg.get("input") or {}
    if inp.get("path"):
        record = record_under_input(data, inp, cwd)
    else:
        record, _ = build_record(data)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_csv(record, path)
    return path.resolve()


def record_under_input(data: dict, inp: dict, cwd: str):
    """The record of ``data``'s truth and noise under the input of the CSV ``inp['path']`` (t, v_in)."""
    from toggle_id.app.records import measure_truth
    from toggle_id.data import read_input
    from toggle_id.errors import ConfigError

    limits = {"v_max": inp.get("v_max", 0.3), "max_duration": inp.get("max_duration", 60.0),
              "rate_hz": data.get("rate_hz", 1000.0), "x_B0": data.get("x_B0", 0.020)}
    for key, value in limits.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ConfigError(f"{key if key in ('rate_hz', 'x_B0') else 'input.' + key} must be a positive number, "
                              f"got {value!r}")
    src = Path(str(inp["path"])).expanduser()
    rec = read_input(src if src.is_absolute() else Path(cwd) / src, **limits)
    measure_truth(rec, data)
    return rec


@hydra.main(config_path="../conf", config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    plain = OmegaConf.to_container(cfg, resolve=True)
    path = guarded(lambda: write_record(plain, get_original_cwd()))
    print(f"report: {path}", flush=True)


if __name__ == "__main__":
    precheck("simulate", sys.argv[1:])
    main()
