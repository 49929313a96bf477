import importlib.metadata
import os
import pathlib
import subprocess
import sys

import jax
import pytest

from rsmooth import _xla


def _version(monkeypatch, version):
    monkeypatch.setattr(importlib.metadata, "version", lambda name: version)


def test_flags_added_once_on_a_known_jaxlib(monkeypatch):
    _version(monkeypatch, "0.10.2")
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert _xla.apply_cpu_defaults(env)  # every command: the loop emitters
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {_xla.EMITTERS_FLAG}=false"
    assert _xla.apply_cpu_defaults(env, render=True)  # the render commands: and no YNNPACK
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {_xla.EMITTERS_FLAG}=false {_xla.YNN_FLAG}="
    assert not _xla.apply_cpu_defaults(env, render=True)  # already there: unchanged
    assert env["XLA_FLAGS"].count(_xla.YNN_FLAG) == 1 and env["XLA_FLAGS"].count(_xla.EMITTERS_FLAG) == 1
    env = {"XLA_FLAGS": f"{_xla.EMITTERS_FLAG}=true"}  # the user's own choice is kept
    assert _xla.apply_cpu_defaults(env, render=True) and env["XLA_FLAGS"] == f"{_xla.EMITTERS_FLAG}=true {_xla.YNN_FLAG}="


@pytest.mark.parametrize(
    "version, env",
    [
        ("0.9.1", {}),  # a jaxlib not known to have the flag (XLA aborts on unknown flags)
        ("0.11.0", {}),
        ("0.10.2", {"RSMOOTH_XLA_DEFAULTS": "0"}),  # the opt-out
        ("0.10.2", {"XLA_FLAGS": f"{_xla.YNN_FLAG}=reduce {_xla.EMITTERS_FLAG}=true"}),  # the user's own choice
    ],
)
def test_flags_left_alone(monkeypatch, version, env):
    _version(monkeypatch, version)
    before = dict(env)
    assert not _xla.apply_cpu_defaults(env, render=True)
    assert env == before


def test_installed_xla_accepts_what_is_added():
    # On the installed jaxlib: whatever apply_cpu_defaults adds, XLA must start with it (an
    # unknown flag aborts the process).
    code = (
        "from rsmooth import _xla; added = _xla.apply_cpu_defaults(render=True); "
        "import jax.numpy as jnp; print(added, float(jnp.sum(jnp.arange(4.0))))"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "RSMOOTH_XLA_DEFAULTS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-1] == "6.0"


def test_resolve_auto_follows_the_backend(monkeypatch):
    monkeypatch.setattr(_xla, "on_accelerator", lambda: False)
    assert _xla.resolve_auto("auto", cpu=4, accelerator=None) == 4
    monkeypatch.setattr(_xla, "on_accelerator", lambda: True)
    assert _xla.resolve_auto("auto", cpu=4, accelerator=None) is None
    assert _xla.resolve_auto(8, cpu=4, accelerator=None) == 8
    assert _xla.resolve_auto(None, cpu=4, accelerator=16) is None


def test_compilation_cache_folder_and_opt_outs(tmp_path):
    home = {"HOME": str(tmp_path)}
    assert _xla.default_cache_dir({**home, "XDG_CACHE_HOME": "/x"}) == pathlib.Path("/x/rsmooth/jax")
    assert _xla.default_cache_dir(home).parts[-3:] == (".cache", "rsmooth", "jax")
    for off in ("0", "off", ""):
        assert _xla.enable_compilation_cache({_xla.CACHE_VARIABLE: off}) is None
    # a cache the user set up for JAX is kept as it is (and JAX's configuration not touched)
    before = jax.config.jax_compilation_cache_dir
    assert str(_xla.enable_compilation_cache({"JAX_COMPILATION_CACHE_DIR": "/mine"})) == "/mine"
    assert jax.config.jax_compilation_cache_dir == before

