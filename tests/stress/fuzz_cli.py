"""Fuzzing the command line: random options and --set values, every rejection one line.

Each invocation runs `mjstamp.cli.main(argv)` in this process with the
expensive work stubbed out (a solve's screen, that is everything after its
up-front checks; a check; the skill recording; view's meshcat server: each
raises `Accepted` when reached), so hundreds of invocations take
seconds; everything before that (argparse, settings typing and validation,
task loading with its settings, results directories, scene loading) is real.
A sample is also run as real subprocesses of the `mjstamp` console script, to
see that no traceback reaches stderr.

Outcomes: `accepted` (reached the stub with valid input), `rejected` (exit 2
and exactly one stderr line `... error: ...`), `ok` (exit 0: --help, `tasks`),
and `crash`: any other exception, another exit status, or a rejection of more
than one line. Accepted solves are also checked for what they were given:
`--set flag=False` must mean False.

Usage: python -m tests.stress.fuzz_cli [--invocations N] [--seed S] [--subprocesses K] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import io
import json
import os
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path

import numpy as np

INTS = ["0", "-1", "1", "2", "3", "7", "64", "99999999999999999999", "1.5", "abc", "", "1e3",
        "٣", "nan", " 4", "--"]
FLOATS = ["0", "-0.5", "1e-3", "0.25", "nan", "inf", "-inf", "abc", "", "1e400", "1,5"]
BOOLS = ["true", "false", "True", "False", "0", "1", "yes", "no", "on", "off", "maybe", "",
         "FALSE", " false "]
STRINGS = ["", "auto", "fwd", "rev", "x" * 300, "ünïcode", "a b", "None", "none", "[1, 2]",
           "1,2", "{}", "../etc/passwd"]


class Accepted(Exception):
    """Reached the expensive work with input the CLI accepted."""


@dataclasses.dataclass
class Report:
    """What the fuzz saw."""

    tried: int = 0
    outcomes: dict = dataclasses.field(default_factory=dict)
    crashes: list = dataclasses.field(default_factory=list)
    tracebacks: int = 0

    def add(self, outcome: str, argv: list[str], detail: str = "") -> None:
        """Counts one invocation (keeps the first 20 crashes)."""
        self.tried += 1
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1
        if outcome == "crash" and len(self.crashes) < 20:
            self.crashes.append({"argv": argv, "detail": detail[-2000:]})


def _settings(task: str) -> dict:
    from mjstamp import registry
    from mjstamp.config import SolveConfig

    defaults = {key: default for key, (default, _) in SolveConfig.leaves().items()}
    defaults.update(registry.default_config(task))
    return defaults


def _value_for(default, rng) -> str:
    if rng.random() < 0.15:  # any type's value for any key
        return str(rng.choice(INTS + FLOATS + BOOLS + STRINGS))
    if isinstance(default, bool):
        return str(rng.choice(BOOLS))
    if isinstance(default, int):
        return str(rng.choice(INTS + [str(default), str(default * 2)]))
    if isinstance(default, float):
        return str(rng.choice(FLOATS + [repr(default), repr(default * 2)]))
    if default is None:
        return str(rng.choice(INTS + FLOATS + ["None", "none"]))
    return str(rng.choice(STRINGS + [str(default)]))


def _set_pairs(task: str, rng) -> list[str]:
    settings = _settings(task)
    keys = sorted(settings)
    out = []
    for _ in range(int(rng.integers(0, 4))):
        r = rng.random()
        if r < 0.1:
            out += ["--set", str(rng.choice(["novalue", "=1", "", "a=b=c", "particles"]))]
            continue
        key = str(rng.choice(keys))
        if r < 0.2:  # misspelt
            key = key[:-1] if len(key) > 3 else key + "x"
        out += ["--set", f"{key}={_value_for(settings.get(key), rng)}"]
    return out


def _paths(root: Path) -> list[str]:
    (root / "empty").mkdir(exist_ok=True)
    (root / "file.txt").write_text("not a results directory")
    (root / "bad.xml").write_text("<mujoco><worldbody><geom type='sphere'/></worldbody")
    (root / "notxml.xml").write_text("\x00\x01binary")
    real = [str(p) for p in sorted(Path("tutorials/results").glob("*")) if p.is_dir()]
    return real + [str(root / "missing"), str(root / "empty"), str(root / "file.txt"), "/dev/null",
            "", str(root / "bad.xml"), str(root / "notxml.xml"), "y" * 300,
            str(root / "file.txt" / "below")]


def random_argv(rng, root: Path) -> list[str]:
    """One random invocation of the `mjstamp` command line."""
    paths = _paths(root)
    command = str(rng.choice(["solve", "solve", "solve", "check", "view", "tasks", "skills",
                              "bogus", ""]))
    tasks_ = ["billiards", "pushing", "nope", "", "BILLIARDS"]
    argv = [command] if command else []
    if command == "solve":
        task = str(rng.choice(tasks_, p=[0.5, 0.3, 0.1, 0.05, 0.05]))
        argv.append(task)
        if rng.random() < 0.5:
            argv += ["--particles", str(rng.choice(INTS))]
        if rng.random() < 0.3:
            argv += ["--seed", str(rng.choice(INTS))]
        if rng.random() < 0.2:
            argv += ["--out", str(rng.choice(paths + [str(root / "out")]))]
        if rng.random() < 0.1:
            argv += ["--resume", str(rng.choice(paths))]
        if rng.random() < 0.1:
            argv += ["--checkpoint-every", str(rng.choice(FLOATS))]
        if rng.random() < 0.2:
            argv += ["--max-pushes", str(rng.choice(INTS))]
        if rng.random() < 0.15:
            argv += ["--devices", str(rng.choice(INTS + ["auto", "AUTO"]))]
        argv += _set_pairs(task if task in ("billiards", "pushing") else "billiards", rng)
        for flag in ("--json", "--no-coverage", "--quiet"):
            if rng.random() < 0.2:
                argv.append(flag)
    elif command == "check":
        argv.append(str(rng.choice(["billiards", "pushing", "nope"] + paths)))
        for flag, bag in (("--particles", INTS), ("--horizon", INTS), ("--iterations", INTS),
                          ("--tolerance", FLOATS), ("--gradient", ["unrolled", "implicit", "x"]),
                          ("--precision", ["float32", "float64", "float16"]),
                          ("--seed", INTS)):
            if rng.random() < 0.3:
                argv += [flag, str(rng.choice(bag))]
    elif command == "view":
        argv.append(str(rng.choice(paths)))
        for flag, bag in (("--plan", INTS), ("--task-plan", STRINGS), ("--task", tasks_),
                          ("--port", INTS), ("--html", [str(root / "o.html"), "/nonexistent/x"])):
            if rng.random() < 0.3:
                argv += [flag, str(rng.choice(bag))]
    elif command == "skills":
        if rng.random() < 0.5:
            argv += ["--out", str(rng.choice(paths + ["/nonexistent/dir/bank.npz"]))]
    if rng.random() < 0.05:
        argv.append(str(rng.choice(["--help", "--bogus", "extra"])))
    return argv


@contextlib.contextmanager
def _stubs(seen: list):
    """The expensive work raises Accepted (a solve records what it was given)."""
    import mjstamp.scenes.check as check_mod
    import mjstamp.solver.pipeline as solve_mod
    import mjstamp.viz.playback as playback

    def initial_particles(problem, cfg, seed, say):  # solve's first expensive step
        seen.append(cfg)
        raise Accepted

    def stop(*args, **kwargs):
        raise Accepted

    saved = {(solve_mod, "_initial_particles"): solve_mod._initial_particles,
             (check_mod, "check_scene"): check_mod.check_scene,
             (check_mod, "check_task"): check_mod.check_task,
             (playback, "start_server"): playback.start_server}
    solve_mod._initial_particles = initial_particles
    check_mod.check_scene = check_mod.check_task = stop
    playback.start_server = stop  # view: all but the meshcat server is real
    from mjstamp import registry

    commands = [c for e in registry.entries().values() for c in e.commands]
    runs = [(c, c.run) for c in commands]
    for c, _ in runs:
        object.__setattr__(c, "run", stop)
    try:
        yield
    finally:
        for (mod, name), fn in saved.items():
            setattr(mod, name, fn)
        for c, fn in runs:
            object.__setattr__(c, "run", fn)


def _expected_bools(argv: list[str]) -> dict[str, bool]:
    """--set KEY=VALUE pairs whose VALUE spells a bool, as the CLI must read them."""
    out = {}
    for flag, pair in zip(argv, argv[1:], strict=False):
        if flag != "--set" or "=" not in pair:
            continue
        key, _, value = pair.partition("=")
        v = value.strip().lower()
        if v in ("true", "1", "yes", "on"):
            out[key] = True
        elif v in ("false", "0", "no", "off"):
            out[key] = False
    return out


def run_one(argv: list[str], report: Report) -> str:
    """Runs one invocation in-process; returns and records its outcome."""
    from mjstamp.cli import main
    from mjstamp.config import SolveConfig

    seen: list = []
    err = io.StringIO()
    outcome, detail = None, ""
    with _stubs(seen), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(list(argv))
        except Accepted:
            outcome = "accepted"
        except SystemExit as e:
            code = e.code
        except BaseException:  # noqa: BLE001 - the fuzz looks for exactly these
            outcome, detail = "crash", traceback.format_exc()
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    if "Traceback" in err.getvalue():
        report.tracebacks += 1
        outcome, detail = "crash", err.getvalue()
    if outcome is None:
        if code == 2 and len(lines) == 1 and "error:" in lines[0]:
            outcome = "rejected"
        elif code == 0:  # --help, `tasks`: nothing expensive to reach
            outcome = "ok"
        else:
            outcome, detail = "crash", f"exit {code}, stderr {err.getvalue()!r}"
    if outcome == "accepted" and seen and isinstance(seen[0], SolveConfig):
        fields = set(SolveConfig.fields())
        for key, want in _expected_bools(argv).items():
            got = functools.reduce(getattr, key.split("."), seen[0]) if key in fields else None
            if isinstance(got, bool) and got is not want:
                outcome, detail = "crash", f"--set {key} read as {got!r}"
    report.add(outcome, argv, detail)
    return outcome


def _subprocess_one(argv: list[str], report: Report) -> None:
    script = Path(sys.executable).with_name("mjstamp")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "mjstamp.cli"]
    proc = subprocess.run(cmd + argv, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    if "Traceback" in proc.stderr:
        report.tracebacks += 1
        report.add("crash", argv, proc.stderr)
    elif proc.returncode == 2 and len(lines) == 1:
        report.add("rejected", argv)
    elif proc.returncode == 0:
        report.add("ok", argv)
    else:
        report.add("crash", argv, f"exit {proc.returncode}, stderr {proc.stderr!r}")


def fuzz_cli(invocations: int, *, seed: int = 0, subprocesses: int = 0,
             say=lambda msg: None) -> dict:
    """Tries `invocations` random command lines in-process and `subprocesses` for real."""
    import mjstamp

    mjstamp.configure()
    rng = np.random.default_rng(seed)
    report, rejected = Report(), []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for i in range(invocations):
            argv = random_argv(rng, root)
            if run_one(argv, report) == "rejected":
                rejected.append(argv)
            if (i + 1) % 100 == 0:
                say(f"[fuzz-cli] {i + 1}/{invocations}: {report.outcomes}")
        sub = Report()
        picks = rng.permutation(len(rejected))[:subprocesses]
        for j, k in enumerate(picks):
            _subprocess_one(rejected[k], sub)
            say(f"[fuzz-cli] subprocess {j + 1}/{len(picks)}: {sub.outcomes}")
    crashes = report.outcomes.get("crash", 0) + sub.outcomes.get("crash", 0)
    return {
        "cli_tried": report.tried, "cli_subprocesses": sub.tried,
        "cli_crashes": crashes, "cli_tracebacks": report.tracebacks + sub.tracebacks,
        "cli_one_line_rejections": report.outcomes.get("rejected", 0),
        "cli_accepted": report.outcomes.get("accepted", 0),
        "cli_outcomes": report.outcomes, "cli_subprocess_outcomes": sub.outcomes,
        "cli_examples": (report.crashes + sub.crashes)[:10],
    }


def main(argv: list[str] | None = None) -> int:
    """Command line of the CLI fuzz."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--invocations", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--subprocesses", type=int, default=20)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    out = fuzz_cli(args.invocations, seed=args.seed, subprocesses=args.subprocesses,
                   say=lambda msg: print(msg, file=sys.stderr, flush=True))
    print(json.dumps(out, indent=None if args.json else 2))
    return 0 if out["cli_crashes"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
