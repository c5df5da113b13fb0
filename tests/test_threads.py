"""Thread policy: passive OpenMP waiting by default, the user's settings win."""

from __future__ import annotations

import pytest

from emlpack.threads import configure_thread_environment, default_threads


def test_defaults_are_passive_and_bounded():
    env: dict = {}
    n = configure_thread_environment(environ=env)
    assert env["OMP_WAIT_POLICY"] == "PASSIVE"
    assert n == int(env["OMP_NUM_THREADS"]) == default_threads()
    assert 1 <= n <= 4
    assert default_threads(64) == 4 and default_threads(1) == 1


def test_user_settings_win_and_explicit_threads_override():
    env = {"OMP_WAIT_POLICY": "ACTIVE", "OMP_NUM_THREADS": "3"}
    assert configure_thread_environment(environ=env) == 3
    assert env["OMP_WAIT_POLICY"] == "ACTIVE"
    assert configure_thread_environment(1, environ=env) == 1
    assert env["OMP_NUM_THREADS"] == "1"
    with pytest.raises(ValueError, match="threads"):
        configure_thread_environment(0, environ=env)
