"""Particles sharded over host devices: the same plans as on one device, to rounding."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

# Solves the tiny task on 1 and on 2 host devices (7 particles: one pad) and prints both.
SCRIPT = f"""
import json, sys
sys.path.insert(0, {str(TESTS)!r})
import mjstamp
mjstamp.configure(devices=2)
import jax
from conftest import make_tiny_task
from mjstamp import solve
out = {{"devices": len(jax.devices())}}
for k in (1, 2):
    cfg = {{"particles": 7, "devices": k,
           "stamp": {{"svgd_max_iters": 6, "sgd_max_iters": 6, "min_iters": 100}}}}
    s = solve(make_tiny_task(), cfg, seed=0, progress=False).summary()
    out[k] = {{"plans": s["plans"], "task_plans": s["task_plans"],
              "verified": s["verified_plans"]}}
print(json.dumps(out))
"""


@pytest.mark.slow
def test_sharded_and_unsharded_solves_agree(same_plans):
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    one, two = out["1"], out["2"]
    # The same plans; costs and motion plans to rounding (a 2-device compile vectorises
    # its smaller batches differently: 1 ulp here, 2e-16).
    same_plans(one, two, atol=1e-12)


def test_more_devices_than_present_is_one_line():
    from mjstamp.errors import MjstampError  # noqa: PLC0415
    from mjstamp.parallel import check_devices  # noqa: PLC0415

    with pytest.raises(MjstampError, match=r"devices=64 but JAX sees \d+ cpu device"):
        check_devices(64)


@pytest.mark.parametrize("argv, needle", [
    (["solve", "billiards", "--devices", "0"], "device count 0 must be >= 1"),
    (["solve", "billiards", "--devices", "two"], "invalid device count 'two'"),
    (["solve", "billiards", "--devices", "4096"], "CPU cores"),
])
def test_bad_devices_flag_is_one_line(argv, needle, capsys):
    from mjstamp.cli import main  # noqa: PLC0415

    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_host_device_count_auto_is_one_per_core_at_most_8_shared_on_one_machine(monkeypatch):
    import os  # noqa: PLC0415

    from mjstamp import parallel  # noqa: PLC0415
    from mjstamp.errors import MjstampError  # noqa: PLC0415

    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert parallel.host_device_count(None) is None
    assert parallel.host_device_count("auto") == 8
    assert parallel.host_device_count(16) == 16
    # N.B. processes of one machine (a loopback coordinator) share its cores; others do not.
    assert parallel.host_device_count("auto", coordinator="127.0.0.1:4321", num_processes=2) == 4
    assert parallel.host_device_count("auto", coordinator="10.0.0.2:4321", num_processes=2) == 8
    with pytest.raises(MjstampError, match="--devices 17: this machine has 16 CPU cores"):
        parallel.host_device_count(17)


def test_shard_count_auto_is_every_device_and_n_is_checked():
    import jax  # noqa: PLC0415

    from mjstamp import parallel  # noqa: PLC0415
    from mjstamp.errors import MjstampError  # noqa: PLC0415

    assert parallel.shard_count("auto") == parallel.shard_count(None) == jax.device_count()
    assert parallel.shard_count(1) == 1
    with pytest.raises(MjstampError, match="devices=64 but JAX sees"):
        parallel.shard_count(64)


def test_configure_devices_auto_keeps_a_running_jax():
    import jax  # noqa: PLC0415

    import mjstamp  # noqa: PLC0415

    before = jax.device_count()  # N.B. JAX runs now: "auto" keeps it, never strict
    mjstamp.configure(devices="auto")
    assert jax.device_count() == before


def test_set_xla_flag_replaces_its_own_and_keeps_the_users_when_asked(monkeypatch):
    from mjstamp.parallel import set_xla_flag

    monkeypatch.setenv("XLA_FLAGS", "--xla_a=1 --xla_cpu_use_fusion_emitters=true")
    assert not set_xla_flag("--xla_cpu_use_fusion_emitters", False, keep_users=True)
    assert os.environ["XLA_FLAGS"] == "--xla_a=1 --xla_cpu_use_fusion_emitters=true"
    assert set_xla_flag("--xla_cpu_use_fusion_emitters", False)
    assert os.environ["XLA_FLAGS"] == "--xla_a=1 --xla_cpu_use_fusion_emitters=false"
    assert set_xla_flag("--xla_force_host_platform_device_count", 2)
    assert os.environ["XLA_FLAGS"].split()[-1] == "--xla_force_host_platform_device_count=2"


@pytest.mark.parametrize(("given", "expected"), [
    ("", "--xla_cpu_use_fusion_emitters=false"),
    ("--xla_cpu_use_fusion_emitters=true", "--xla_cpu_use_fusion_emitters=true"),
])
def test_configure_turns_cpu_fusion_emitters_off_unless_the_user_set_them(given, expected):
    code = ("import os, mjstamp; mjstamp.configure(compilation_cache=False); "
            "import jax; jax.numpy.zeros(1); print(os.environ['XLA_FLAGS'])")
    env = {**os.environ, "XLA_FLAGS": given}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == [expected]
