"""The public face (`from mjstamp import ...`) and the old paths that still work for a release."""

import subprocess
import sys
import warnings

import pytest


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-W", "default::DeprecationWarning", "-c", code],
                          capture_output=True, text=True, check=True)


def test_the_face_names_what_a_user_writes_without_importing_jax_first():
    out = _run(
        "import sys, mjstamp\n"
        "assert 'jax' not in sys.modules, 'import mjstamp imported JAX'\n"
        "from mjstamp import Scene, SolveConfig, Task, costs, load, solve\n"
        "from mjstamp.scenes.scene import Scene as S\n"
        "from mjstamp.solver.pipeline import solve as f\n"
        "from mjstamp.tasks.task import Task as T\n"
        "assert (Scene, solve, Task) == (S, f, T)\n"
        "assert SolveConfig(particles=3).particles == 3\n"
        "assert callable(costs.reach) and callable(load)\n"
        "print(sorted(set(mjstamp.__all__) - set(dir(mjstamp))))\n")
    assert out.stdout.strip() == "[]"
    assert "Deprecation" not in out.stderr, out.stderr


def test_an_unknown_name_is_an_attribute_error():
    import mjstamp

    with pytest.raises(AttributeError, match="no attribute 'Solve'"):
        mjstamp.Solve  # noqa: B018


@pytest.mark.parametrize(("old", "new"), [
    ("from mjstamp.solve import solve, SolveConfig", "mjstamp.solver"),
    ("import mjstamp.scenes.contacts as c; c.PORTED", "mjstamp.colliders"),
    ("from mjstamp.scenes.contacts import gjk", "mjstamp.colliders"),
    ("from mjstamp.scenes.distance import make_distance_fn", "mjstamp.distance"),
    ("from mjstamp.tasks import load", "mjstamp.registry.load"),
    ("from mjstamp.tasks import parse_overrides", "mjstamp.cli.settings.parse_overrides"),
    ("from mjstamp.modes import random_search", "mjstamp.baselines.sampling.random_search"),
    ("from mjstamp.results import summarize", "mjstamp.solver.summary.summarize"),
])
def test_an_old_path_works_and_says_where_it_went_at_the_users_line(old, new):
    err = _run(old + "\n").stderr
    lines = [line for line in err.splitlines() if "DeprecationWarning" in line]
    assert len(lines) == 1, err  # one line, attributed to the line the user wrote
    assert lines[0].startswith("<string>:1: DeprecationWarning:"), err
    assert f"moved to {new}" in lines[0], err


def test_the_old_module_solve_is_still_the_solve():
    # N.B. in a subprocess: importing the stub makes `mjstamp.solve` the module for the session.
    out = _run("import mjstamp.solve as old\n"
               "from mjstamp.solver import pipeline\n"
               "assert old.solve is pipeline.solve\n"
               "assert callable(old)  # mjstamp.solve(task, config) once the stub is imported\n"
               "print('ok')\n")
    assert out.stdout.strip() == "ok"


def test_an_old_module_is_the_new_one_so_its_state_exists_once():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mjstamp.scenes.contacts import PORTED, gjk

    from mjstamp import colliders
    from mjstamp.colliders import gjk as new_gjk

    assert PORTED is colliders.PORTED and gjk is new_gjk
