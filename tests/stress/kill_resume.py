"""Kill -9 at random points of a small solve, resume, and compare with a run never stopped.

The solve is the billiards task made small (`--particles 16`, 10 + 10
iterations, a checkpoint after every iteration), run as a user runs it: the
`mjstamp` console script. Each trial starts it, waits until its checkpoint
reaches a random iteration, sleeps a random fraction of a second more (so the
kill lands anywhere: mid-step, mid-write of the checkpoint), sends SIGKILL, and
resumes with `--resume DIR`. A trial passes when the resumed plans.json equals
the uninterrupted one apart from timings.

Usage: python -m tests.stress.kill_resume [--trials 10] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mjstamp import checkpoint
from mjstamp.errors import MjstampError

ITERS = 10
ARGS = ["solve", "billiards", "--particles", "16", "--set", f"stamp.svgd_max_iters={ITERS}",
        "--set", f"stamp.sgd_max_iters={ITERS}", "--set", "stamp.min_iters=100", "--no-coverage",
        "--quiet",
        "--checkpoint-every", "0", "--json"]
VOLATILE = ("wall_time_s", "timings", "iteration_seconds", "compiles")


def _mjstamp() -> list[str]:
    script = Path(sys.executable).with_name("mjstamp")
    return [str(script)] if script.exists() else [sys.executable, "-m", "mjstamp.cli"]


def stable_plans(out: Path) -> dict:
    """plans.json without what varies between runs (timings)."""
    data = json.loads((out / "plans.json").read_text())
    for key in VOLATILE:
        data.pop(key, None)
    # N.B. the calibration's seconds, and whether it came from its cache: the first
    # solve on a machine calibrates, the ones after it read the cache.
    for key in ("us_per_particle_step", "seconds", "cached"):
        data["fidelity"].pop(key, None)
    for section in ("screen", "robustness"):
        if data.get(section):
            data[section].pop("seconds", None)
            data[section].pop("first_seen_s", None)
    for part in (data.get("polish") or {}).values():
        if part:
            part.pop("seconds", None)
    data.pop("first_plan_s", None)
    for plan in (data.get("found") or {}).values():
        plan.pop("seconds", None)
    return data


def _progress(out: Path) -> int:
    """Iterations done according to the checkpoint in `out` (0: none readable yet)."""
    try:
        meta = checkpoint.read_meta(out)
    except MjstampError:
        return 0
    return meta["iteration"] + (ITERS if meta["phase"] == 1 else 0)


def trial(out: Path, kill_at: int, delay: float, reference: dict) -> dict:
    """One kill -9 at iteration `kill_at` (+ `delay` s), then a resume; what happened."""
    proc = subprocess.Popen(_mjstamp() + ARGS + ["--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    started = time.monotonic()
    while _progress(out) < kill_at and proc.poll() is None:
        time.sleep(0.02)
    time.sleep(delay)
    finished_first = proc.poll() is not None
    proc.kill()
    proc.wait()
    killed_after = _progress(out)
    row = {"kill_at_iteration": kill_at, "delay_s": round(delay, 3),
           "checkpoint_iteration_at_kill": killed_after, "finished_before_kill": finished_first}
    if (out / "plans.json").exists() and not (out / checkpoint.FILENAME).exists():
        # The solve ended before the kill landed: nothing to resume.
        row.update(resume_exit=None, same_plans=stable_plans(out) == reference)
    else:
        resumed = subprocess.run(_mjstamp() + ARGS + ["--resume", str(out)],
                                 capture_output=True, text=True)
        row.update(resume_exit=resumed.returncode,
                   resume_stderr_tail=resumed.stderr.strip().splitlines()[-1:],
                   same_plans=resumed.returncode == 0 and stable_plans(out) == reference)
    row["seconds"] = round(time.monotonic() - started, 1)
    return row


def main(argv: list[str] | None = None) -> int:
    """Command line of the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    say = lambda msg: print(f"[kill-resume] {msg}", file=sys.stderr, flush=True)  # noqa: E731
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t = time.monotonic()
        ref = subprocess.run(_mjstamp() + ARGS + ["--out", str(root / "ref")],
                             capture_output=True, text=True)
        if ref.returncode != 0:
            raise SystemExit(f"reference solve failed: {ref.stderr.strip()[-500:]}")
        reference = stable_plans(root / "ref")
        say(f"reference solve: {time.monotonic() - t:.1f} s, "
            f"{reference['verified_plans']} verified plans")
        trials = []
        for i in range(args.trials):
            kill_at = int(rng.integers(1, 2 * ITERS))
            delay = float(rng.uniform(0.0, 0.3))
            trials.append(trial(root / f"t{i}", kill_at, delay, reference))
            say(f"trial {i + 1}/{args.trials}: {trials[-1]}")
    out = {"task": "billiards (16 particles, 10 + 10 iterations)", "trials": len(trials),
           "resumed_with_same_plans": sum(t["same_plans"] for t in trials),
           "reference_verified_plans": reference["verified_plans"], "detail": trials}
    print(json.dumps(out, indent=None if args.json else 2))
    return 0 if out["resumed_with_same_plans"] == out["trials"] else 1


if __name__ == "__main__":
    sys.exit(main())
