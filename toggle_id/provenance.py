"""Which code made a result: the package's version and, when it runs from a git checkout of the project, the
commit and whether the checkout had uncommitted changes. Every job's report carries it (``code``); MLflow tags
its runs with the commit by itself (``mlflow.source.git.commit``)."""
from __future__ import annotations

import functools
import subprocess
from importlib import metadata
from pathlib import Path


def _git(root: Path, *args: str) -> str | None:
    try:
        proc = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


@functools.lru_cache(maxsize=1)
def code_version() -> dict:
    """``{"version": …}`` plus ``git_commit`` and ``git_dirty`` (tracked files changed) from a checkout. Only the
    project's own checkout is asked — the directory above the package holding its ``pyproject.toml`` — so an
    installed copy inside some other repository (a virtual environment in a work tree) is never given that
    repository's commit."""
    try:
        version = metadata.version("toggle-id")
    except metadata.PackageNotFoundError:
        version = None
    out: dict = {"version": version}
    root = Path(__file__).resolve().parent.parent
    if (root / "pyproject.toml").is_file() and (root / "toggle_id").is_dir():
        top = _git(root, "rev-parse", "--show-toplevel")
        if top and Path(top).resolve() == root:
            out["git_commit"] = _git(root, "rev-parse", "HEAD")
            status = _git(root, "status", "--porcelain", "--untracked-files=no")
            out["git_dirty"] = None if status is None else bool(status)
    return out
