"""The command line under fuzzing: every rejection one line with exit 2, no traceback."""

import pathlib
import sys

import pytest

from mjstamp.cli import main
from mjstamp.cli.settings import parse_overrides

# The fuzz lives in tests/stress/: import it from the repository root.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from tests.stress.fuzz_cli import fuzz_cli  # noqa: E402 - after the path set-up above


def test_random_command_lines_never_crash():
    """300 random invocations (everything before a solve's screen is real) and 3 subprocesses."""
    out = fuzz_cli(300, seed=0, subprocesses=3)
    assert out["cli_crashes"] == 0, out["cli_examples"]
    assert out["cli_tracebacks"] == 0
    # Not vacuous: most are rejected, some reach the solve, a few run for real.
    assert out["cli_one_line_rejections"] > 100 and out["cli_accepted"] > 20
    assert out["cli_subprocess_outcomes"] == {"rejected": 3}


@pytest.mark.parametrize("text, want", [("False", False), ("false", False), ("0", False),
                                        ("no", False), ("True", True), ("on", True)])
def test_set_bool_means_what_it_says(text, want):
    key = "verify.keep_visited"
    assert parse_overrides("billiards", [f"{key}={text}"])[key] is want


@pytest.mark.parametrize("text, want", [("2.5", 2.5), ("3", 3.0), ("auto", "auto")])
def test_set_cost_scale_takes_a_number_or_auto(text, want):
    # N.B. billiards has a setting of its own named beta (its soft indicators'):
    # the solve setting is cost_scale, and reaches SolveConfig from any task.
    key = "screen.cost_scale"
    assert parse_overrides("billiards", [f"{key}={text}"])[key] == want


@pytest.mark.parametrize("argv, needle", [
    (["solve", "billiards", "--set", "screen.cost_scale=0"],
     "screen.cost_scale=0.0 must be a number > 0"),
    (["solve", "billiards", "--set", "screen.cost_scale=hot"],
     "screen.cost_scale='hot' must be a number > 0"),
    (["solve", "billiards", "--set", "particles=1"], "particles=1 must be an integer >= 2"),
    (["solve", "billiards", "--set", "particles=100000000"], "must be at most 65536"),
    (["solve", "billiards", "--seed", "-1"], "seed -1 must be in 0.."),
    (["solve", "billiards", "--seed", "99999999999999999999"], "must be in 0.."),
    (["solve", "pushing", "--max-pushes", "99999999999999999999"], "must be in 1..10"),
    (["solve", "pushing", "--set", "push_steps=7"], "push_steps=7 must be >= 39 steps"),
    (["solve", "pushing", "--set", "approach_steps=99999999999999999999"], "must be <= 12000"),
    (["solve", "pushing", "--set", "skill_bank=" + "x" * 300], "cannot be read"),
    (["view", "y" * 300], "cannot be read"),
    (["check", "billiards", "--particles", "10000000"], "must be in 1..65536"),
    (["solve", "billiards", "--particles", "abc"], "invalid int value"),
    (["check", "billiards", "--iterations", "99999999999999999999"], "must be in 1..10000"),
    (["check", "tiny.xml", "--horizon", "99999999999999999999"], "must be in 1..100000"),
])
def test_found_by_the_fuzz_now_one_line(argv, needle, capsys):
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
