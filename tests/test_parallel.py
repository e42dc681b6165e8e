"""Particles sharded over host devices: the same plans as on one device, to rounding."""

import json
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
from mjstamp.solve import solve
out = {{"devices": len(jax.devices())}}
for k in (1, 2):
    cfg = {{"particles": 7, "svgd_max_iters": 6, "sgd_max_iters": 6, "min_iters": 100,
           "devices": k}}
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
