"""Checkpoint and resume of a solve: kill -9, SIGTERM, refusals, reproducible plans.json."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mjstamp import checkpoint
from mjstamp.errors import MjstampError

pytestmark = pytest.mark.slow  # solves (compiles the tiny task's steps)

TESTS = Path(__file__).resolve().parent
CONFIG = {"particles": 8, "stamp": {"svgd_max_iters": 8, "sgd_max_iters": 8, "min_iters": 100}}

# Solves the tiny task with a checkpoint after every iteration; argv: DIR [resume] [slow].
SCRIPT = f"""
import sys, time
sys.path.insert(0, {str(TESTS)!r})
from conftest import make_tiny_task
from mjstamp import checkpoint
from mjstamp import solve
out, resume, slow = sys.argv[1], "resume" in sys.argv, "slow" in sys.argv
if slow:  # a pause per checkpoint, so a signal can land mid-solve
    save = checkpoint.save
    checkpoint.save = lambda *a, **k: (save(*a, **k), time.sleep(0.3))
try:
    r = solve(make_tiny_task(), {CONFIG!r}, seed=0, checkpoint_dir=out, resume=resume,
              checkpoint_every_s=0, progress=False, resume_hint="RESUME")
except KeyboardInterrupt as e:
    print(e, file=sys.stderr)
    sys.exit(130)
r.save(out, figures=False)
"""

# plans.json without what varies between runs (timings): the kill-and-resume benchmark's.
sys.path.insert(0, str(TESTS.parent))
from mjstamp.solver import FOUND_FILE  # noqa: E402
from tests.stress.kill_resume import stable_plans as _stable  # noqa: E402


def _start(out: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-c", SCRIPT, str(out), *extra], env=env,
                            stderr=subprocess.PIPE, text=True)


def _wait_for(out: Path, proc: subprocess.Popen, *, phase: int, iteration: int) -> None:
    """Waits until the checkpoint in `out` is past (phase, iteration)."""
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read()
        if (out / checkpoint.FILENAME).is_file():
            try:
                meta = checkpoint.read_meta(out)
            except MjstampError:  # between writes
                meta = None
            if meta and (meta["phase"], meta["iteration"]) >= (phase, iteration):
                return
        time.sleep(0.05)
    raise AssertionError("no checkpoint in time")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """plans.json of a solve never stopped (and what its directory holds after)."""
    out = tmp_path_factory.mktemp("straight")
    proc = _start(out)
    assert proc.wait(timeout=900) == 0, proc.stderr.read()
    assert not (out / checkpoint.FILENAME).exists()  # spent once plans.json is written
    return _stable(out)


def test_the_same_seed_gives_the_same_plans_json(reference, tmp_path):
    proc = _start(tmp_path)
    assert proc.wait(timeout=900) == 0, proc.stderr.read()
    again = _stable(tmp_path)
    assert again == reference, [k for k in reference if again.get(k) != reference[k]]


@pytest.mark.parametrize("phase, iteration", [(0, 3), (1, 2)])
def test_killed_by_sigkill_then_resumed_ends_with_the_same_plans(reference, tmp_path, phase,
                                                                 iteration):
    proc = _start(tmp_path, "slow")
    _wait_for(tmp_path, proc, phase=phase, iteration=iteration)
    proc.kill()
    proc.wait()
    assert not (tmp_path / "plans.json").exists()
    resumed = _start(tmp_path, "resume")
    assert resumed.wait(timeout=900) == 0, resumed.stderr.read()
    assert _stable(tmp_path) == reference


def test_sigterm_writes_a_checkpoint_and_says_how_to_continue(reference, tmp_path):
    proc = _start(tmp_path, "slow")
    _wait_for(tmp_path, proc, phase=0, iteration=2)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 130
    message = proc.stderr.read().strip().splitlines()[-1]
    assert "SIGTERM" in message and "checkpoint of" in message and "RESUME" in message
    assert checkpoint.read_meta(tmp_path)["task"] == "tiny"
    # What the screen had verified before the signal is kept beside the checkpoint.
    kept = json.loads((tmp_path / FOUND_FILE).read_text())
    assert kept and all(f["source"] in ("screen", "landed early") for f in kept.values())
    resumed = _start(tmp_path, "resume")
    assert resumed.wait(timeout=900) == 0, resumed.stderr.read()
    assert _stable(tmp_path) == reference


def test_a_checkpoint_of_other_settings_is_refused_in_one_line(tmp_path, tiny_task):
    from mjstamp import solve  # noqa: PLC0415
    from mjstamp.config import SolveConfig  # noqa: PLC0415

    problem = tiny_task().build()
    # The checkpoint of the same solve with 16 particles instead of 8.
    # N.B. checkpoints hash the flat view, so ones written before the nesting resume.
    solve_settings = {**SolveConfig.from_dict({**CONFIG, "particles": 16}).flat_dict(),
                      "devices": 1}
    settings = {"task": dict(problem.settings), "solve": solve_settings}
    snap_meta = {"task": "tiny", "version": checkpoint.__version__, "settings": settings,
                 "seed": 0, "fingerprint": checkpoint.fingerprint(problem.fingerprint, settings, 0)}
    _fake_checkpoint(tmp_path, snap_meta)
    with pytest.raises(MjstampError, match="solve setting particles was 16, is 8") as e:
        solve(problem, CONFIG, seed=0, checkpoint_dir=tmp_path, resume=True, progress=False)
    assert "\n" not in str(e.value)
    with pytest.raises(MjstampError, match="seed was 0, is 1"):
        solve(problem, {**CONFIG, "particles": 16}, seed=1, checkpoint_dir=tmp_path,
              resume=True, progress=False)
    _fake_checkpoint(tmp_path, {**snap_meta, "version": "0.0.1"})
    with pytest.raises(MjstampError, match="another mjstamp version"):
        solve(problem, CONFIG, seed=0, checkpoint_dir=tmp_path, resume=True, progress=False)
    _fake_checkpoint(tmp_path, {**snap_meta, "task": "billiards"})
    with pytest.raises(MjstampError, match="another task"):
        solve(problem, CONFIG, seed=0, checkpoint_dir=tmp_path, resume=True, progress=False)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "missing"])
def test_a_damaged_checkpoint_is_one_line(tmp_path, damage):
    _fake_checkpoint(tmp_path, {"task": "tiny"})
    path = tmp_path / checkpoint.FILENAME
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:100])
    elif damage == "garbage":
        path.write_bytes(b"not a zip")
    else:
        path.unlink()
    with pytest.raises(MjstampError) as e:
        checkpoint.read_meta(tmp_path)
    assert "\n" not in str(e.value) and str(path.parent) in str(e.value)


def _fake_checkpoint(out: Path, meta: dict) -> None:
    import numpy as np  # noqa: PLC0415

    from mjstamp.svgd import LoopSnapshot  # noqa: PLC0415

    snap = LoopSnapshot(phase=0, iteration=1, particles=np.zeros((8, 2)), opt_leaves=[],
                        key_data=np.zeros(2, np.uint32), rows=[], svgd_particles=None,
                        svgd_converged=None,
                        counters={k: np.zeros(8, int) for k in
                                  ("stalled", "rescued", "failing", "nonfinite_redrawn")})
    checkpoint.save(out / checkpoint.FILENAME, snap, meta)


def _cli(capsys, *argv):
    from mjstamp.cli import main  # noqa: PLC0415

    code = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    return code, err


def test_cli_refuses_to_overwrite_an_unfinished_solve(tmp_path, capsys):
    _fake_checkpoint(tmp_path, {"task": "billiards", "format": 1})
    code, err = _cli(capsys, "solve", "billiards", "--out", str(tmp_path))
    assert code == 2 and len(err) == 1
    assert "unfinished solve of task 'billiards'" in err[0] and "--resume" in err[0]


@pytest.mark.parametrize("argv, match", [
    (["--out", "A", "--resume", "B"], "differ"),
    (["--checkpoint-every", "-1"], "must be >= 0"),
    (["--resume", "NOWHERE"], "holds no checkpoint.npz"),
])
def test_cli_checkpoint_flags_bad_input_is_one_line(tmp_path, capsys, argv, match):
    argv = [a if a not in ("A", "B", "NOWHERE") else str(tmp_path / a) for a in argv]
    code, err = _cli(capsys, "solve", "billiards", *argv)
    assert code == 2 and len(err) == 1 and match in err[0]


def test_resume_hint_is_the_same_command_with_resume():
    from mjstamp.cli.solve import resume_hint  # noqa: PLC0415

    hint = resume_hint(["solve", "billiards", "--seed", "3", "--out", "R", "--set", "a=1"], "R")
    assert hint == "mjstamp solve billiards --seed 3 --set a=1 --resume R"


def test_a_signal_after_the_last_checkpoint_call_still_stops(tmp_path):
    """SIGTERM between the last iteration and the end of STAMP is not lost."""
    previous = signal.getsignal(signal.SIGTERM)
    ck = checkpoint.Checkpointer(tmp_path, {"task": "tiny"}, every_s=1e9, resume_hint="RESUME")
    with pytest.raises(checkpoint.Interrupted, match="SIGTERM as STAMP ended.*RESUME"):
        with ck.catch_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
    assert signal.getsignal(signal.SIGTERM) is previous
