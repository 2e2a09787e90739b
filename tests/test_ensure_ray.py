"""ensure_ray starts a local cluster lean and joins clusters as before (ray.init recorded, not run)."""

from __future__ import annotations

from typing import Any

import pytest
import ray
import ray._private.services as services

from pipelines.runner import ensure_ray, ray_connection


@pytest.fixture
def init_calls(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    calls: list[dict[str, Any]] = []
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", lambda **kwargs: calls.append(kwargs))
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    return calls


def test_local_cluster_starts_lean_with_a_fresh_config_each_time(init_calls, monkeypatch) -> None:
    monkeypatch.setattr(services, "canonicalize_bootstrap_address", lambda addr, temp_dir=None: None)
    assert ensure_ray(None, {"env_vars": {"A": "1"}}) is True
    assert ensure_ray("local") is True
    first, second = init_calls
    assert first["address"] is None and first["runtime_env"] == {"env_vars": {"A": "1"}}
    assert second["address"] == "local"
    for call in init_calls:
        assert "include_dashboard" not in call  # Ray Train's placement-group cleaner needs its State API
        assert call["_system_config"] == {"enable_metrics_collection": False, "event_stats": False}
    assert first["_system_config"] is not second["_system_config"]  # ray.init writes into the dict it gets


@pytest.mark.parametrize("how", ["argument", "environment", "running cluster"])
def test_joining_a_cluster_passes_no_local_settings(init_calls, monkeypatch, how: str) -> None:
    monkeypatch.setattr(services, "canonicalize_bootstrap_address", lambda addr, temp_dir=None: "10.0.0.1:6379")
    if how == "environment":
        monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    assert ensure_ray("10.0.0.1:6379" if how == "argument" else None) is True
    expected = None if how == "running cluster" else "10.0.0.1:6379"
    assert init_calls == [{"address": expected, "runtime_env": None}]


def test_already_connected_does_nothing(monkeypatch) -> None:
    monkeypatch.setattr(ray, "is_initialized", lambda: True)
    monkeypatch.setattr(ray, "init", lambda **kwargs: pytest.fail("ray.init called"))
    assert ensure_ray("10.0.0.1:6379") is False


def test_ray_connection_connects_once_and_shuts_down_what_it_started(monkeypatch) -> None:
    """A stage with several runs connects once; the runs inside find Ray connected (and leave it up)."""
    state = {"connected": False, "inits": 0, "shutdowns": 0}

    def init(**kwargs: Any) -> None:
        state["connected"], state["inits"] = True, state["inits"] + 1

    def shutdown() -> None:
        state["connected"], state["shutdowns"] = False, state["shutdowns"] + 1

    monkeypatch.setattr(ray, "is_initialized", lambda: state["connected"])
    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setattr(ray, "shutdown", shutdown)
    monkeypatch.setattr(services, "canonicalize_bootstrap_address", lambda addr, temp_dir=None: None)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    with ray_connection({"num_workers": 1}):
        assert state == {"connected": True, "inits": 1, "shutdowns": 0}
        assert [ensure_ray(None) for _ in range(3)] == [False, False, False]  # what each run's call sees
    assert state == {"connected": False, "inits": 1, "shutdowns": 1}
    with ray_connection({"num_workers": 0}), ray_connection({"num_workers": 2, "local": True}):
        assert state["inits"] == 1  # in-process runs need no Ray
    with pytest.raises(RuntimeError), ray_connection({"num_workers": 1}):
        raise RuntimeError("a run failed")
    assert state == {"connected": False, "inits": 2, "shutdowns": 2}  # shut down on failure too
