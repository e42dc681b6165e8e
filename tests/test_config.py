"""`SolveConfig`: nested groups, dotted keys, the flat names of before (deprecated)."""

import dataclasses
import warnings

import pytest

from mjstamp.cli.settings import parse_overrides
from mjstamp.config import (
    FLAT_NAMES,
    SOLVE_STAMP,
    SettingDeprecationWarning,
    SolveConfig,
)
from mjstamp.errors import MjstampError
from mjstamp.svgd import StampConfig


def _no_warning(fn):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn()


def test_nested_dict_dotted_key_and_group_object_give_the_same_config():
    want = _no_warning(lambda: SolveConfig(stamp=dataclasses.replace(SOLVE_STAMP,
                                                                     backtrack=False)))
    assert want.stamp.backtrack is False and want.stamp.svgd_max_iters == 50
    assert _no_warning(lambda: SolveConfig.from_dict({"stamp": {"backtrack": False}})) == want
    assert _no_warning(lambda: SolveConfig.from_dict({"stamp.backtrack": False})) == want
    assert _no_warning(lambda: SolveConfig(stamp={"backtrack": False})) == want


def test_as_dict_is_nested_json_and_round_trips():
    import json

    cfg = SolveConfig.from_dict({"particles": 16, "robust.draws": 4, "screen.candidates": 1})
    d = json.loads(json.dumps(cfg.as_dict()))
    assert d["robust"] == {"draws": 4, "cvar": 1.0, "select": 0} and d["screen"]["candidates"] == 1
    assert "seed" not in d["stamp"]  # the solve's own seed
    assert _no_warning(lambda: SolveConfig.from_dict(d)) == cfg


def test_flat_dict_has_the_thirty_names_of_before():
    flat = SolveConfig().flat_dict()
    assert len(flat) == 30 and set(flat) == {"particles", "devices", *FLAT_NAMES}
    assert flat["screen"] == 64 and flat["robust"] == 0 and flat["calibrate"] is True


@pytest.mark.parametrize(("old", "value"), [
    ("backtrack", False), ("screen", 1), ("robust", 3), ("robust_cvar", 0.5),
    ("calibrate", False), ("keep_visited", False), ("cost_scale", 2.0),
])
def test_a_flat_name_still_works_with_one_deprecation_line(old, value):
    new = FLAT_NAMES[old]
    group, field = new.split(".")
    for make in (lambda: SolveConfig.from_dict({old: value}),
                 lambda: SolveConfig(**{old: value})):
        with pytest.warns(SettingDeprecationWarning) as caught:
            cfg = make()
        assert len(caught) == 1
        message = str(caught[0].message)
        assert f"'{old}'" in message and f"'{new}'" in message and "\n" not in message
        assert issubclass(caught[0].category, DeprecationWarning)
        assert getattr(getattr(cfg, group), field) == value


def test_later_keys_win_and_a_base_is_kept():
    cfg = SolveConfig.from_dict({"stamp": {"min_iters": 3}, "stamp.min_iters": 4})
    assert cfg.stamp.min_iters == 4
    base = SolveConfig.from_dict({"stamp.window": 7})
    assert SolveConfig.from_dict({"stamp": {"min_iters": 3}}, base=base).stamp.window == 7


@pytest.mark.parametrize(("config", "needle"), [
    ({"stamp.backtrak": True}, "did you mean 'stamp.backtrack'"),
    ({"backtrak": True}, "did you mean 'stamp.backtrack'"),
    ({"screen": {"candidate": 2}}, "did you mean 'screen.candidates'"),
    ({"stamp.seed": 3}, "unknown solve setting 'stamp.seed'"),
    ({"stamp.svgd_max_iters": -1}, "stamp.svgd_max_iters must be an integer >= 0"),
    ({"stamp.motion_tol": -1.0}, "stamp.motion_tol must be a float >= 0 or None"),
    ({"screen.candidates": 0}, "screen.candidates=0 must be an integer >= 1"),
    ({"verify.repair": "yes"}, "verify.repair='yes' must be True or False"),
    ({"calibration.max_solver_iterations": 0}, "calibration.max_solver_iterations=0"),
    ({"robust.cvar": 0}, "robust.cvar=0 must be a number in (0, 1]"),
])
def test_bad_keys_and_values_are_one_line_naming_the_dotted_key(config, needle):
    with pytest.raises(MjstampError) as e:
        SolveConfig.from_dict(config)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_stamp_config_validates_once_with_the_library_error():
    with pytest.raises(MjstampError, match="window must be an integer >= 1"):
        StampConfig(window=0)
    with pytest.raises(MjstampError, match="stamp.seed=2"):
        SolveConfig(stamp=StampConfig(seed=2))
    with pytest.raises(MjstampError, match="a schedule goes to svgd.run_stamp"):
        SolveConfig(stamp=dataclasses.replace(SOLVE_STAMP, svgd_learning_rate=lambda t: t))


def test_run_stamp_refuses_what_the_caller_had_to_resolve():
    import jax.numpy as jnp

    from mjstamp.svgd import run_stamp

    def flat(x):
        return jnp.zeros(x.shape[0]), jnp.zeros((x.shape[0], 0))

    with pytest.raises(MjstampError, match="config.motion_tol"):
        run_stamp(flat, jnp.zeros((4, 2)), config=StampConfig(motion_tol=None), progress=False)
    with pytest.raises(MjstampError, match="config.svgd_learning_rate"):
        run_stamp(flat, jnp.zeros((4, 2)), config=StampConfig(svgd_learning_rate=None),
                  progress=False)


def test_set_types_dotted_keys_and_keeps_flat_ones():
    got = parse_overrides("billiards", ["stamp.backtrack=false", "screen.cost_scale=auto",
                                        "robust.cvar=0.5", "calibration.fidelity_tolerance=none",
                                        "backtrack=off", "screen=2"])
    assert got == {"stamp.backtrack": False, "screen.cost_scale": "auto", "robust.cvar": 0.5,
                   "calibration.fidelity_tolerance": None, "backtrack": False, "screen": 2}
    with pytest.raises(MjstampError, match="expected int"):
        parse_overrides("billiards", ["stamp.svgd_max_iters=x"])
    with pytest.raises(MjstampError, match="no such setting"):
        parse_overrides("billiards", ["stamp.nope=1"])


def test_the_cli_prints_the_deprecation_in_one_line(capsys):
    from mjstamp.cli import main

    # N.B. an invalid value of another setting stops the solve before any work.
    assert main(["solve", "billiards", "--set", "backtrack=false", "--set", "particles=1"]) == 2
    err = capsys.readouterr().err
    assert "mjstamp: warning: solve setting 'backtrack' is now 'stamp.backtrack'" in err
    assert "particles=1 must be an integer >= 2" in err


def test_a_task_loads_with_nested_overrides():
    from mjstamp import registry

    _, cfg = _no_warning(lambda: registry.load("billiards", **{"stamp.backtrack": False},
                                            screen={"candidates": 2}))
    assert cfg.stamp.backtrack is False and cfg.screen.candidates == 2
    assert cfg.stamp.svgd_max_iters == 40 and cfg.stamp.jacobian == "fwd"  # billiards' own


def test_the_deprecation_is_attributed_to_the_line_the_user_wrote():
    """A DeprecationWarning shows only where it is attributed to the user's own code."""
    from mjstamp import registry

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        registry.load("billiards", backtrack=False)
        cfg = SolveConfig.from_dict({"keep_visited": False})
        assert cfg.repair_rounds == cfg.verify.repair_rounds  # a flat read, deprecated too
    assert [w.filename for w in caught] == [__file__] * 3, [(w.filename, w.lineno) for w in caught]
    assert all(issubclass(w.category, SettingDeprecationWarning) for w in caught)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        SolveConfig().nope  # noqa: B018
