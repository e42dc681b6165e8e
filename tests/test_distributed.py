"""One solve over several processes (jax.distributed on localhost CPU, Gloo)."""

import json
import shlex
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from mjstamp.cli import main

TESTS = Path(__file__).resolve().parent
README = TESTS.parent / "README.md"
MJSTAMP = str(Path(sys.executable).with_name("mjstamp"))

# The tiny task, 7 particles, alone or as process I of 2 (one host device each).
SCRIPT = f"""
import json, sys
sys.path.insert(0, {str(TESTS)!r})
import mjstamp
port, pid = sys.argv[1], int(sys.argv[2])
if pid < 0:
    mjstamp.configure()
else:
    mjstamp.configure(coordinator=f"127.0.0.1:{{port}}", num_processes=2, process_id=pid)
import jax
from conftest import make_tiny_task
from mjstamp import solve
cfg = {{"particles": 7, "stamp": {{"svgd_max_iters": 6, "sgd_max_iters": 6, "min_iters": 100}}}}
s = solve(make_tiny_task(), cfg, seed=0, progress=False).summary()
print(json.dumps({{"devices": s["devices"], "processes": jax.process_count(),
                  "verified": s["verified_plans"], "task_plans": s["task_plans"],
                  "plans": s["plans"]}}))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


@pytest.mark.slow
def test_two_processes_give_the_plans_of_one(same_plans):
    port = str(_free_port())
    procs = [subprocess.Popen([sys.executable, "-c", SCRIPT, port, str(pid)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for pid in (-1, 1, 0)]
    outs = [p.communicate(timeout=900) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
    alone, one, zero = (_last_json(out) for out, _ in outs)
    assert (alone["processes"], alone["devices"]) == (1, 1)
    assert (zero["processes"], zero["devices"]) == (2, 2)
    assert zero == one  # every process ends with the same result
    same_plans(zero, alone, atol=1e-12)


def _readme_commands(port: int, out: Path) -> list[list[str]]:
    """The README's two-process example, on a free port, writing into `out`."""
    lines = [line.strip().rstrip("&").strip() for line in README.read_text().splitlines()
             if "--coordinator 127.0.0.1:4321" in line and line.startswith("      ")]
    assert len(lines) == 2, lines
    commands = []
    for line in lines:
        argv = shlex.split(line.replace("127.0.0.1:4321", f"127.0.0.1:{port}"))
        assert argv[0] == ".venv/bin/mjstamp"
        argv[0] = MJSTAMP
        if "--out" in argv:
            argv[argv.index("--out") + 1] = str(out)
        commands.append(argv)
    return commands


@pytest.mark.slow
def test_readme_two_process_example_runs(tmp_path):
    out = tmp_path / "two"
    commands = _readme_commands(_free_port(), out)
    procs = [subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              cwd=tmp_path) for argv in commands]
    outs = [p.communicate(timeout=900) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
    (follower_out, follower_err), (lead_out, _) = outs
    assert "--process-id 1" in shlex.join(commands[0])
    # Process 0 prints the table and writes; process 1 says nothing on stdout.
    assert "distinct verified task plans" in lead_out
    assert follower_out == ""
    summary = json.loads((out / "plans.json").read_text())
    assert summary["devices"] == 2
    assert not (out / "checkpoint.npz").exists()


@pytest.mark.parametrize("argv, needle", [
    (["--process-id", "1"], "--num-processes and --process-id need --coordinator"),
    (["--coordinator", "127.0.0.1:4321"], "--coordinator needs --num-processes N"),
    (["--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"],
     "coordinator='nohost' must be HOST:PORT"),
    (["--coordinator", "127.0.0.1:70000", "--num-processes", "2", "--process-id", "0"],
     "port in 1..65535"),
    (["--coordinator", "127.0.0.1:4321", "--num-processes", "2", "--process-id", "2"],
     "process_id=2 must be an integer in [0, 2)"),
    (["--coordinator", "127.0.0.1:4321", "--num-processes", "0", "--process-id", "0"],
     "process count 0 must be >= 1"),
    (["--coordinator", "127.0.0.1:4321", "--num-processes", "2", "--process-id", "x"],
     "invalid process id 'x'"),
    (["--coordinator", "127.0.0.1:4321", "--num-processes", "2", "--process-id", "0",
      "--coordinator-timeout", "inf"], "coordinator timeout inf must be a finite number"),
    (["--coordinator", "127.0.0.1:4321", "--num-processes", "2", "--process-id", "0",
      "--coordinator-timeout", "-1"], "coordinator timeout -1 must be a finite number"),
])
def test_bad_process_flags_are_one_line(argv, needle, capsys):
    assert main(["solve", "billiards", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([MJSTAMP, *argv], capture_output=True, text=True, timeout=120)


def test_unreachable_coordinator_is_one_line():
    port = _free_port()  # nobody listens there
    proc = _run(["solve", "billiards", "--coordinator", f"127.0.0.1:{port}",
                 "--num-processes", "2", "--process-id", "1", "--coordinator-timeout", "1"])
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1, proc.stderr[-2000:]
    assert f"coordinator 127.0.0.1:{port} not reachable within 1 s" in err[0]


def test_coordinator_port_taken_is_one_line():
    with socket.create_server(("", 0)) as taken:
        port = taken.getsockname()[1]
        proc = _run(["solve", "billiards", "--coordinator", f"127.0.0.1:{port}",
                     "--num-processes", "2", "--process-id", "0"])
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1, proc.stderr[-2000:]
    assert f"process 0 cannot listen on port {port}" in err[0]
