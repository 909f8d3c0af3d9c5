"""jaxcal's XLA defaults (`jaxcal._xla`): which flags are added, and when the user's choice wins."""

import subprocess
import sys

import pytest
from jax._src import xla_bridge

from jaxcal import _xla


@pytest.fixture
def fresh(monkeypatch):
    """`configure_xla` as before a backend starts, on an environment of the test's own."""
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    monkeypatch.delenv("JAXCAL_XLA_DEFAULTS", raising=False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    return monkeypatch


@pytest.mark.parametrize(("cores", "split"), [(2, True), (4, True), (16, False)])
def test_the_codegen_split_is_dropped_on_few_cores(fresh, cores, split):
    fresh.setattr(_xla, "_cores", lambda: cores)
    added = _xla.configure_xla()
    assert added == [_xla.FUSION_EMITTERS_OFF] + ([_xla.ONE_CODEGEN_PART] if split else [])
    assert _xla.os.environ["XLA_FLAGS"] == " ".join(added)


def test_the_users_flags_win_and_the_opt_out_adds_nothing(fresh):
    fresh.setattr(_xla, "_cores", lambda: 2)
    fresh.setenv("XLA_FLAGS", "--xla_cpu_parallel_codegen_split_count=8")
    assert _xla.configure_xla() == [_xla.FUSION_EMITTERS_OFF]
    assert (
        _xla.os.environ["XLA_FLAGS"] == f"--xla_cpu_parallel_codegen_split_count=8 {_xla.FUSION_EMITTERS_OFF}"
    )
    fresh.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    fresh.setenv("JAXCAL_XLA_DEFAULTS", "0")
    assert _xla.configure_xla() == []
    assert _xla.os.environ["XLA_FLAGS"] == "--xla_backend_optimization_level=0"


def test_a_flag_this_jaxlib_does_not_know_is_not_added(fresh):
    """XLA aborts the process on an unknown flag: only names found in jaxlib's binaries are added."""
    assert _xla._jaxlib_knows(["xla_cpu_use_fusion_emitters", "xla_cpu_no_such_flag_at_all"]) == {
        "xla_cpu_use_fusion_emitters"
    }
    fresh.setattr(_xla, "defaults", lambda: ["--xla_cpu_no_such_flag_at_all=true"])
    assert _xla.configure_xla() == []
    assert "XLA_FLAGS" not in _xla.os.environ


def test_a_fresh_process_starts_with_the_defaults():
    """The flags reach XLA: a process that imports jaxcal runs with them (an unknown flag would abort it)."""
    code = "import os, jax, jaxcal; jax.numpy.ones(2).block_until_ready(); print(os.environ['XLA_FLAGS'])"
    env = {k: v for k, v in _xla.os.environ.items() if k not in ("XLA_FLAGS", "JAXCAL_XLA_DEFAULTS")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == _xla.defaults()
