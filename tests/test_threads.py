"""Thread and BLAS policy: passive OpenMP waiting by default, AVX2 kernels for PySCF's OpenBLAS, the
user's settings win."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from emlpack.threads import (
    configure_openblas_coretype,
    configure_thread_environment,
    default_threads,
)
from tests.conftest import require


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


def test_openblas_coretype_only_for_avx2_cpus_and_never_over_the_user(tmp_path):
    cpu = tmp_path / "cpuinfo"
    cpu.write_text("processor : 0\nflags : fpu sse4_2 avx fma avx2 avx512f\n")
    env: dict = {}
    assert configure_openblas_coretype(env, str(cpu)) == "Haswell"
    assert env == {"OPENBLAS_CORETYPE": "Haswell"}
    user = {"OPENBLAS_CORETYPE": "Zen"}
    assert configure_openblas_coretype(user, str(cpu)) == "Zen"
    assert user["OPENBLAS_CORETYPE"] == "Zen"
    cpu.write_text("flags : fpu sse4_2 avx\n")
    env = {}
    assert configure_openblas_coretype(env, str(cpu)) is None and env == {}
    assert configure_openblas_coretype({}, str(tmp_path / "missing")) is None


def test_pyscf_openblas_runs_the_requested_kernels():
    """A labeler, made before PySCF is imported, gets PySCF's bundled OpenBLAS the AVX2
    kernels (it reports its core by ``openblas_get_corename``) on an AVX2 CPU."""
    require("pyscf")
    code = """
import os
from emlpack.qm.pyscf_labeler import PySCFLabeler
from emlpack.threads import pyscf_openblas_core
PySCFLabeler("tiny")
print(os.environ.get("OPENBLAS_CORETYPE"), pyscf_openblas_core() or "no-bundled-openblas")
"""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=Path(__file__).resolve().parents[1], check=True).stdout.split()
    if out[1] == "no-bundled-openblas":
        pytest.skip("this PySCF build has no bundled OpenBLAS")
    if out[0] == "Haswell":
        assert out[1].lower() == "haswell", out
