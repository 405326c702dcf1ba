"""Tests of toggle_id.tracking: a real SQLite MLflow store (one per module: opening it costs seconds)."""
from __future__ import annotations

import os
import socket
import time
import warnings

import numpy as np
import pytest

from toggle_id.errors import ConfigError
from toggle_id.tracking import (MAX_METRICS_PER_BATCH, MAX_PARAM_VAL_LENGTH, PARENT_TAG, Tracker, TrackingWarning,
                                absolute_uri, default_artifact_location, default_tracking_uri, flatten, sanitize_key)

pytestmark = pytest.mark.filterwarnings("ignore:.*noload.*")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return tmp_path_factory.mktemp("store")


@pytest.fixture(scope="module")
def tracker(store):
    with warnings.catch_warnings():
        warnings.simplefilter("error", TrackingWarning)
        tr = Tracker(default_tracking_uri(store), "toggle-id-test")
    assert tr.ok, tr.error
    return tr


@pytest.fixture(autouse=True)
def _fresh_drops(request):
    """Each test starts with an empty dropped-list on the shared tracker."""
    if "tracker" in request.fixturenames:
        request.getfixturevalue("tracker").clear_dropped()
    yield


def _runs(tr: Tracker) -> list:
    return tr.client.search_runs([tr.experiment_id], max_results=1000)


# ---------------------------------------------------------------------------------------------- URIs


def test_default_uri_is_absolute_sqlite(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    uri = default_tracking_uri("proj")
    assert uri == "sqlite:///" + str(tmp_path / "proj" / "mlflow.db")
    assert uri.startswith("sqlite:////")  # four slashes: an absolute path
    assert default_artifact_location(uri) == "file://" + str(tmp_path / "proj" / "mlruns")


def test_absolute_uri_resolves_relative_paths(tmp_path):
    root = str(tmp_path)
    assert absolute_uri("sqlite:///sub/x.db", root) == "sqlite:///" + os.path.join(root, "sub", "x.db")
    assert absolute_uri("sqlite:////abs/x.db", root) == "sqlite:////abs/x.db"
    assert absolute_uri("x.db", root) == "sqlite:///" + os.path.join(root, "x.db")
    assert absolute_uri("stores", root) == default_tracking_uri(os.path.join(root, "stores"))
    assert absolute_uri(None, root) == default_tracking_uri(root)
    assert absolute_uri("http://host:5000", root) == "http://host:5000"
    assert absolute_uri("file:mlruns", root) == "file://" + os.path.join(root, "mlruns")


def test_flatten_and_sanitize():
    assert flatten({"ga": {"pop": 50, "p": {"c": 0.7}}, "x": [1, 2]}) == {"ga.pop": 50, "ga.p.c": 0.7, "x": [1, 2]}
    assert sanitize_key("rms [µm]") == "rms _µm_"
    assert sanitize_key("/a//b") == "a/b"
    assert len(sanitize_key("k" * 400)) == 250


def test_bad_config_raises():
    with pytest.raises(ConfigError):
        Tracker(None, "", enabled=False)
    with pytest.raises(ConfigError):
        Tracker(None, "x", enabled=False, http_timeout_s=0)


# -------------------------------------------------------------------------------------- logging


def test_params_metrics_and_history(tracker):
    hist = 1e6 * (1.0 - np.exp(-np.arange(150) / 30.0))
    with tracker.run("basic", tags={"stage": 1, "x [mm]": "y"}) as run:
        assert tracker.run_id == run.run_id is not None
        tracker.log_params({"ga": {"population": 50, "pc": 0.7, "bounds": np.array([0.0, 1.0])},
                            "long": "y" * (MAX_PARAM_VAL_LENGTH + 500)})
        tracker.log_metrics({"rms_um": np.float64(1.25), "stage": {"fitness": 3.0}}, step=7)
        tracker.log_metric_history("best_fitness", hist)
    assert tracker.run_id is None
    data = tracker.client.get_run(run.run_id).data
    assert data.params["ga.population"] == "50"
    assert data.params["ga.pc"] == "0.7"
    assert data.params["ga.bounds"] == "[0.0, 1.0]"
    assert len(data.params["long"]) == MAX_PARAM_VAL_LENGTH
    assert data.tags["stage"] == "1" and data.tags["x _mm_"] == "y"
    assert data.metrics["rms_um"] == 1.25 and data.metrics["stage.fitness"] == 3.0
    assert [m.step for m in tracker.client.get_metric_history(run.run_id, "stage.fitness")] == [7]
    series = sorted(tracker.client.get_metric_history(run.run_id, "best_fitness"), key=lambda m: m.step)
    assert [m.step for m in series] == list(range(150))
    np.testing.assert_allclose([m.value for m in series], hist)
    assert tracker.client.get_run(run.run_id).info.status == "FINISHED"
    assert not tracker.dropped


def test_history_is_batched(tracker, monkeypatch):
    calls = []
    original = tracker.client.log_batch

    def spy(run_id, metrics=(), params=(), tags=(), synchronous=None):
        calls.append(len(metrics))
        return original(run_id, metrics=metrics, params=params, tags=tags, synchronous=synchronous)

    monkeypatch.setattr(tracker.client, "log_batch", spy)
    n = 2 * MAX_METRICS_PER_BATCH + 150
    with tracker.run("batched") as run:
        tracker.log_metric_history("h", np.arange(n, dtype=float), start_step=10)
    assert calls == [MAX_METRICS_PER_BATCH, MAX_METRICS_PER_BATCH, 150]
    steps = sorted(m.step for m in tracker.client.get_metric_history(run.run_id, "h"))
    assert steps == list(range(10, 10 + n))


def test_nested_children_have_parent_tag(tracker):
    with tracker.run("parent") as parent:
        with tracker.run("child-1", nested=True) as c1:
            tracker.log_metrics({"x": 1.0})
        with tracker.run("child-2", nested=True) as c2:
            assert tracker.run_id == c2.run_id
        assert tracker.run_id == parent.run_id
    assert len({parent.run_id, c1.run_id, c2.run_id}) == 3
    for child in (c1, c2):
        info = tracker.client.get_run(child.run_id)
        assert info.data.tags[PARENT_TAG] == parent.run_id
        assert info.info.run_name == child.name
    assert PARENT_TAG not in tracker.client.get_run(parent.run_id).data.tags
    assert "x" in tracker.client.get_run(c1.run_id).data.metrics
    assert "x" not in tracker.client.get_run(parent.run_id).data.metrics


def test_resume_continues_the_same_run(tracker):
    with tracker.run("resumable") as first:
        tracker.log_params({"seed": 1})
        tracker.log_metric_history("best", [1.0, 2.0, 3.0])
    before = len(_runs(tracker))
    with tracker.run("resumable", run_id=first.run_id) as again:
        assert again.resumed and again.run_id == first.run_id
        assert tracker.client.get_run(first.run_id).info.status == "RUNNING"
        tracker.log_params({"seed": 1})  # identical value: accepted
        tracker.log_metric_history("best", [4.0, 5.0], start_step=3)
    assert len(_runs(tracker)) == before
    assert tracker.client.get_run(first.run_id).info.status == "FINISHED"
    steps = sorted((m.step, m.value) for m in tracker.client.get_metric_history(first.run_id, "best"))
    assert steps == [(0, 1.0), (1, 2.0), (2, 3.0), (3, 4.0), (4, 5.0)]
    assert not tracker.dropped


def test_resume_unknown_run_starts_new_one(tracker):
    before = len(_runs(tracker))
    with tracker.run("lost", run_id="0" * 32) as run:
        assert not run.resumed and run.run_id not in (None, "0" * 32)
    assert len(_runs(tracker)) == before + 1
    assert tracker.client.get_run(run.run_id).data.tags["toggle_id.resume_requested"] == "0" * 32
    assert tracker.ok


def test_changed_param_is_dropped_not_fatal(tracker):
    with tracker.run("params") as run:
        tracker.log_params({"a": 1})
        tracker.log_params({"a": 2})
        tracker.log_metrics({"after": 1.0})
    assert tracker.ok
    assert tracker.client.get_run(run.run_id).data.metrics["after"] == 1.0
    assert [d.op for d in tracker.dropped] == ["log_params"]


def test_failed_body_marks_run_failed_and_propagates(tracker):
    with pytest.raises(RuntimeError, match="boom"):
        with tracker.run("failing") as run:
            raise RuntimeError("boom")
    assert tracker.client.get_run(run.run_id).info.status == "FAILED"
    assert tracker.run_id is None


def test_artifacts(tracker, tmp_path):
    from matplotlib.figure import Figure

    fig = Figure()
    fig.subplots().plot([0, 1], [0, 1])
    local = tmp_path / "table.csv"
    local.write_text("a,b\n1,2\n")
    with tracker.run("artifacts") as run:
        tracker.log_dict({"theta": np.arange(3.0), "n": np.int64(2)}, "result.json")
        tracker.log_text("hello", "notes/readme.txt")
        tracker.log_figure(fig, "fig.png")
        tracker.log_artifact(local)
        tracker.log_artifact(tmp_path / "missing.csv")  # refused, not fatal
    assert tracker.ok
    names = {f.path for f in tracker.client.list_artifacts(run.run_id)}
    assert {"result.json", "notes", "fig.png", "table.csv"} <= names
    art_dir = tracker.client.download_artifacts(run.run_id, "result.json", str(tmp_path / "dl"))
    with open(art_dir, encoding="utf-8") as fh:
        assert "".join(fh.read().split()) == '{"theta":[0.0,1.0,2.0],"n":2}'
    assert [d.op for d in tracker.dropped] == ["log_artifact"]


def test_calls_outside_a_run_are_dropped(tracker):
    tracker.log_metrics({"orphan": 1.0})
    assert tracker.ok and [d.reason for d in tracker.dropped] == ["no active run"]


# ----------------------------------------------------------------------------------- resilience


def _exercise(tr: Tracker) -> object:
    with tr.run("outer") as run:
        tr.log_params({"a": 1})
        tr.log_metrics({"m": 1.0}, step=1)
        tr.log_metric_history("h", [1.0, 2.0, 3.0])
        with tr.run("inner", nested=True) as inner:
            tr.set_tags({"t": "v"})
            tr.log_text("x", "x.txt")
        assert inner.run_id is None
    return run


def test_unwritable_store_does_not_raise(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tr = Tracker(default_tracking_uri(blocker / "sub"), "e")
        assert not tr.ok and tr.client is None
        run = _exercise(tr)
    ours = [w for w in caught if issubclass(w.category, TrackingWarning)]
    assert len(ours) == 1, [str(w.message) for w in ours]
    assert "connect failed" in str(ours[0].message)
    assert run.run_id is None and tr.run_id is None
    ops = [d.op for d in tr.dropped]
    assert ops.count("log_metric_history") == 1 and ops.count("start_run") == 2
    assert "log_params ×1" in tr.dropped_summary()
    assert not os.path.exists(blocker / "sub")


def test_store_failure_mid_run_disables_tracking(store, monkeypatch):
    tr = Tracker(default_tracking_uri(store), "toggle-id-test")
    assert tr.ok

    def broken(*args, **kwargs):
        raise OSError("disk full")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with tr.run("midrun") as run:
            tr.log_metrics({"before": 1.0})
            monkeypatch.setattr(tr.client, "log_batch", broken)
            tr.log_metric_history("h", np.arange(5.0))
            assert not tr.ok
            tr.log_metrics({"after": 2.0})
            tr.log_text("t", "t.txt")
            with tr.run("child", nested=True) as child:
                assert child.run_id is None
    ours = [w for w in caught if issubclass(w.category, TrackingWarning)]
    assert len(ours) == 1 and "disk full" in str(ours[0].message)
    assert "log_metric_history" in str(ours[0].message)
    assert [(d.op, d.items) for d in tr.dropped][:3] == [("log_metric_history", 5), ("log_metrics", 1),
                                                          ("log_text", 1)]
    monkeypatch.undo()
    data = tr.client.get_run(run.run_id).data
    assert "before" in data.metrics and "after" not in data.metrics


def test_unresponsive_server_gives_up_quickly(monkeypatch):
    for name in ("MLFLOW_HTTP_REQUEST_TIMEOUT", "MLFLOW_HTTP_REQUEST_MAX_RETRIES",
                 "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR"):
        monkeypatch.delenv(name, raising=False)
    silent = socket.socket()  # accepts connections, never answers
    silent.bind(("127.0.0.1", 0))
    silent.listen(8)
    try:
        t0 = time.perf_counter()
        with pytest.warns(TrackingWarning):
            tr = Tracker(f"http://127.0.0.1:{silent.getsockname()[1]}", "e", http_timeout_s=1, http_max_retries=0)
        elapsed = time.perf_counter() - t0
    finally:
        silent.close()
    assert not tr.ok
    assert elapsed < 15.0
    assert "MLFLOW_HTTP_REQUEST_TIMEOUT" not in os.environ  # scoped to the call


def test_a_file_store_uri_says_how_to_fix_it_in_one_warning(tmp_path, monkeypatch):
    """MLflow 3 refuses ``file:`` stores; the warning names the two ways out instead of a truncated message."""
    monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE", raising=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tr = Tracker(f"file://{tmp_path / 'mlruns'}", "e")
        _exercise(tr)
    if tr.ok:
        pytest.skip("this MLflow still accepts file stores")
    ours = [str(w.message) for w in caught if issubclass(w.category, TrackingWarning)]
    assert len(ours) == 1, ours
    assert "sqlite:////" in ours[0] and "MLFLOW_ALLOW_FILE_STORE=true" in ours[0] and "…" not in ours[0]


def test_disabled_tracker_is_a_no_op():
    tr = Tracker("sqlite:////nonexistent/dir/never.db", "e", enabled=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with tr.run("r", nested=True) as run:
            tr.log_params({"a": 1})
            tr.log_metric_history("h", [1.0])
            tr.log_figure(object(), "f.png")
    assert run.run_id is None and not tr.ok and tr.dropped == [] and tr.dropped_summary() == ""
