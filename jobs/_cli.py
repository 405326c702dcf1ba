"""Shared plumbing of the Hydra entry points: one-line errors and a non-zero exit for bad input.

Hydra reports a configuration it cannot compose (an unknown key, a bad override) in several lines; before
handing over to Hydra the command line is composed once here, so such mistakes end in one line naming the
problem and exit status 2. Errors the library raises for bad input (:class:`toggle_id.errors.ToggleIdError`)
are printed the same way.

Run directories: ``conf/config.yaml`` names a job's directory ``outputs/<date>/<time>-<suffix>`` through the
``unique_dir`` resolver registered here; the directory is created exclusively, so no job writes into another's.
"""
from __future__ import annotations

import os
import secrets
import sys
from pathlib import Path
from typing import Callable

from omegaconf import OmegaConf

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def unique_dir(base: str) -> str:
    """Create ``<base>-<6 random hex digits>`` exclusively and return it (the ``unique_dir`` config resolver).

    ``os.mkdir`` fails when the directory exists, so two jobs started in the same second (the same
    ``outputs/<date>/<time>`` base) never share a run directory: a name already taken is drawn again.
    """
    parent = Path(base).parent
    parent.mkdir(parents=True, exist_ok=True)
    for _ in range(64):
        path = f"{base}-{secrets.token_hex(3)}"
        try:
            os.mkdir(path)
        except FileExistsError:
            continue
        return path
    raise RuntimeError(f"no free run directory name next to {base}")


def register_resolvers() -> None:
    """``${unique_dir:BASE}`` in the Hydra configs (conf/config.yaml's run and sweep directories). Cached, so
    Hydra resolving the same directory twice (a multirun's jobs share their sweep directory) gets one name."""
    if not OmegaConf.has_resolver("unique_dir"):
        OmegaConf.register_new_resolver("unique_dir", unique_dir, use_cache=True)


register_resolvers()  # importing the CLI plumbing (every entry point does) makes the configs resolvable
from jobs import schema  # noqa: E402,F401 — ... and registers the typed nodes (conf/ names them as schema/<node>)


def fail(message: str, code: int = 2) -> None:
    """Print ``error: message`` on one line to stderr and exit with ``code``."""
    print(f"error: {' '.join(str(message).split())}", file=sys.stderr)
    raise SystemExit(code)


def _one_line(exc: BaseException) -> str:
    parts = [str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__]
    cause = exc.__cause__
    if cause is not None and str(cause).strip():
        parts.append(str(cause).strip().splitlines()[0])
    return " — ".join(parts)


def precheck(config_name: str, argv: list[str]) -> None:
    """Compose the configuration from the command line once; a failure is a one-line error, exit 2.

    Skipped for Hydra's own flags (``--help``, ``-m``/``--multirun`` sweeps, ``--cfg`` ...), which Hydra handles.
    """
    if any(a.startswith("-") for a in argv):
        return
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            compose(config_name=config_name, overrides=argv, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException, ValueError) as exc:
        fail(f"bad configuration: {_one_line(exc)}")


def guarded(fn: Callable[[], object]) -> object:
    """Run ``fn``; library input errors become one line on stderr and exit status 2."""
    from toggle_id.errors import ToggleIdError

    try:
        return fn()
    except ToggleIdError as exc:
        fail(str(exc))
    except FileNotFoundError as exc:
        fail(f"file not found: {exc.filename or exc}")
    return None
