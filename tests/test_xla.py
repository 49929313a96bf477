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
    assert _xla.apply_cpu_defaults(env)  # every command: the loop emitters and the plain scheduler
    every = f"{_xla.EMITTERS_FLAG}=false {_xla.SCHEDULER_FLAG}=false"
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {every}"
    assert _xla.apply_cpu_defaults(env, render=True)  # the render commands: and no YNNPACK
    assert env["XLA_FLAGS"] == f"--xla_force_host_platform_device_count=2 {every} {_xla.YNN_FLAG}="
    assert not _xla.apply_cpu_defaults(env, render=True)  # already there: unchanged
    assert all(env["XLA_FLAGS"].count(flag) == 1 for flag in (_xla.YNN_FLAG, _xla.EMITTERS_FLAG, _xla.SCHEDULER_FLAG))
    env = {"XLA_FLAGS": f"{_xla.EMITTERS_FLAG}=true"}  # the user's own choice is kept
    assert _xla.apply_cpu_defaults(env, render=True)
    assert env["XLA_FLAGS"] == f"{_xla.EMITTERS_FLAG}=true {_xla.SCHEDULER_FLAG}=false {_xla.YNN_FLAG}="


@pytest.mark.parametrize(
    "version, env",
    [
        ("0.9.1", {}),  # a jaxlib not known to have the flag (XLA aborts on unknown flags)
        ("0.11.0", {}),
        ("0.10.2", {"RSMOOTH_XLA_DEFAULTS": "0"}),  # the opt-out
        ("0.10.2", {"XLA_FLAGS": f"{_xla.YNN_FLAG}=reduce {_xla.EMITTERS_FLAG}=true {_xla.SCHEDULER_FLAG}=true"}),  # the user's own choice
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



@pytest.mark.skipif(_xla.memory_maps() is None, reason="no /proc: the kernel's map count is Linux's")
def test_released_programs_give_back_their_memory_maps_and_compile_again():
    import numpy as np

    functions = [jax.jit(lambda x, i=i: x * i + 1.0) for i in range(40)]
    first = [float(f(np.float64(2.0))) for f in functions]  # 40 programs, about six maps each
    before, limit = _xla.memory_maps()
    assert not _xla.release_compiled_programs(fraction=1.0)  # far below the kernel's bound: kept
    assert _xla.release_compiled_programs(fraction=before / limit / 2)
    after, _ = _xla.memory_maps()
    assert after < before - 100
    assert [float(f(np.float64(2.0))) for f in functions] == first == [2.0 * i + 1.0 for i in range(40)]


def test_device_array_converts_without_compiling():
    import numpy as np

    compiled = []

    def listener(event, seconds, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(seconds)

    values = np.arange(7 * 13, dtype=np.float64).reshape(7, 13)  # a shape no other test converts
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        array = _xla.device_array(values)
        integers = _xla.device_array([1, 2], np.int32)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiled == [] and array.dtype == np.float64 and np.array_equal(np.asarray(array), values)
    assert integers.dtype == np.int32 and integers.tolist() == [1, 2]
