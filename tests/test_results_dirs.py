"""Damaged results directories: one `MjstampError` line, never a traceback.

Each case damages a copy of a valid results directory (written by `results.save`
from a synthetic solve of the tiny conftest task: every key `SolveResult.summary()`
and `arrays()` write, states replayed in MuJoCo C, no MJX and no solve) and checks
`mjstamp.load(DIR)` and `mjstamp view DIR --html OUT` (exit 2, exactly one
stderr line, the library's message, no page written).
"""

import io
import json
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest

import mjstamp
from mjstamp import results
from mjstamp.cli import main
from mjstamp.errors import MjstampError

T = 40  # steps per plan (the tiny task's horizon)
# particle: (initial puck velocity, task plan of its C replay, verified, cost)
PLANS = {
    0: ((1.5, 0.2), "1-goal", True, 0.4),
    1: ((-1.0, 1.0), "0-goal", True, 0.2),
    3: ((-0.9, 1.1), "0-goal", True, 0.3),
    4: ((0.5, -1.5), "0-goal", False, 2.5),
}
N = 6  # particles; 2 and 5 were not returned
ITERS = 5


def _replay(m, qvel0):
    d = mujoco.MjData(m)
    d.qvel[:] = qvel0
    qpos0, qvel0 = d.qpos.copy(), d.qvel.copy()
    out = {k: [] for k in ("qpos", "qvel", "ctrl", "xpos")}
    for _ in range(T):
        mujoco.mj_step(m, d)
        mujoco.mj_kinematics(m, d)
        for k in out:
            out[k].append(np.array(getattr(d, k)))
    return qpos0, qvel0, {k: np.array(v) for k, v in out.items()}


def _summary(m) -> dict:
    """What `SolveResult.summary()` writes for the tiny task, with these plans."""
    returned = sorted(PLANS)
    verified = [p for p in returned if PLANS[p][2]]
    rows = [
        {"task_plan": "0-goal", "code": "0", "plans": 3, "verified": 2, "repaired": 0,
         "verified_share": 2 / 3, "best_cost": 0.2},
        {"task_plan": "1-goal", "code": "1", "plans": 1, "verified": 1, "repaired": 0,
         "verified_share": 1.0, "best_cost": 0.4},
    ]
    entries = [
        {"particle": p, "task_plan": PLANS[p][1], "predicted_task_plan": PLANS[p][1],
         "verified": PLANS[p][2], "repaired": False, "source": "svgd", "cost": PLANS[p][3],
         "motion_plan": {"v": list(PLANS[p][0])}}
        for p in returned
    ]
    return {
        "task": "tiny", "particles": N, "seed": 0, "wall_time_s": 1.5,
        "timings": {"total_s": 1.5}, "returned_plans": len(returned),
        "verified_plans": len(verified), "repaired_plans": 0,
        "verified_fraction": len(verified) / len(returned),
        "verified_particle_share": len(verified) / N, "distinct_verified_task_plans": 2,
        "distinct_verified_codes": 2, "verified_codes": ["0", "1"], "fidelity": {},
        "screen": None, "rescue": None, "kept_from_earlier": {"svgd": 3, "initial": 0, "screen": 0},
        "task_plans": rows, "plans": entries,
        "iteration_seconds": {"svgd_first": 1.0, "svgd_median": 0.01, "sgd_first": None,
                              "sgd_median": None},
        "stamp": {"svgd_iters": ITERS, "sgd_iters": 0, "svgd_converged": True,
                  "sgd_converged": False},
        "config": {"particles": N, "seed": 0},
        "declaration": {
            "name": "tiny", "scene": "tiny", "horizon": T,
            "timestep": float(m.opt.timestep),
            "variables": [{"name": "v", "kind": "box", "size": 2, "low": [-2, -2],
                           "high": [2, 2]}],
            "symbols": ["wall"], "costs": {"goal": 50.0}, "priors": {},
            "display": {"trace": ["puck"], "force": [["puck", "wall"]]},
        },
    }


def _arrays(m) -> dict:
    """What `SolveResult.arrays()` writes: particles.npz and trajectories.npz."""
    rng = np.random.default_rng(0)
    theta = rng.uniform(-2, 2, (N, 2))
    for p, (v, *_) in PLANS.items():
        theta[p] = v
    returned = np.isin(np.arange(N), sorted(PLANS))
    plan = np.array([PLANS.get(i, (None, "0-goal"))[1] for i in range(N)])
    particles = {
        "theta": theta, "svgd_theta": theta, "initial_theta": rng.uniform(-2, 2, (N, 2)),
        "cost": rng.uniform(0, 3, N), "returned": returned,
        "verified": np.array([PLANS.get(i, (0, 0, False))[2] for i in range(N)]),
        "repaired": np.zeros(N, bool), "source": np.full(N, "svgd"), "task_plan": plan,
        "predicted_task_plan": plan, "logdensity_mean": rng.normal(size=ITERS),
        "logdensity_max": rng.normal(size=ITERS), "phase": np.zeros(ITERS, np.int32),
        "displacement": rng.uniform(size=ITERS), "step_seconds": rng.uniform(size=ITERS),
    }
    runs = [_replay(m, PLANS[p][0]) for p in sorted(PLANS)]
    trajectories = {
        "particle": np.flatnonzero(returned),
        "qpos0": np.array([r[0] for r in runs]), "qvel0": np.array([r[1] for r in runs]),
        **{k: np.array([r[2][k] for r in runs]) for k in ("qpos", "qvel", "ctrl", "xpos")},
        "timestep": np.float64(m.opt.timestep),
    }
    return {"particles": particles, "trajectories": trajectories}


@pytest.fixture(scope="module")
def valid(tmp_path_factory, tiny_xml):
    """A complete results directory of the tiny task (4 returned plans of 6 particles)."""
    out = tmp_path_factory.mktemp("tiny_results")
    m = mujoco.MjModel.from_xml_string(tiny_xml())
    results.save(out, _summary(m), _arrays(m), model=m)
    return out


@pytest.fixture
def copy(valid, tmp_path):
    """A fresh copy of the valid directory, to damage."""
    out = tmp_path / "results"
    shutil.copytree(valid, out)
    return out


def _one_line(path: Path, capfd, *, task: str | None = None) -> str:
    """The one-line error of `mjstamp.load(path)`, checked to be what `mjstamp view` prints."""
    capfd.readouterr()
    with pytest.raises(MjstampError) as info:
        mjstamp.load(path, task=task)
    message = str(info.value)
    assert message and "\n" not in message, message
    assert capfd.readouterr().err == ""  # nothing else on stderr (MuJoCo's warnings)
    page = path.parent / "page.html"
    argv = ["view", str(path), "--html", str(page)] + (["--task", task] if task else [])
    assert main(argv) == 2
    err = capfd.readouterr().err
    assert "Traceback" not in err
    assert err == f"mjstamp: error: {message}\n", err  # exactly one line
    assert not page.exists()
    return message


def _json(path: Path) -> dict:
    return json.loads((path / "plans.json").read_text())


def _write_json(path: Path, data) -> None:
    (path / "plans.json").write_text(json.dumps(data))


def _rewrite_npz(path: Path, name: str, change) -> None:
    with np.load(path / f"{name}.npz") as f:
        arrays = {k: f[k] for k in f.files}
    change(arrays)
    np.savez_compressed(path / f"{name}.npz", **arrays)


def _offsets(size: int, count: int = 8) -> list[int]:
    """Cut points: the ends and `count` more drawn with a fixed seed."""
    rng = np.random.default_rng(size)
    return sorted({0, 1, size // 2, size - 1, *rng.integers(1, size - 1, count).tolist()})


def _rerun(path: Path) -> str:
    return f"re-run `mjstamp solve tiny --out {path}`"


# ----------------------------------------------------------------------------
# The valid directory itself.


def test_valid_directory_loads_and_plays(valid, tmp_path, capfd):
    res = mjstamp.load(valid, task="tiny")
    assert res.task == "tiny" and res.trajectories["qpos"].shape == (len(PLANS), T, 2)
    assert "task tiny: 6 particles" in results.format_table(res.summary)
    page = tmp_path / "page.html"
    capfd.readouterr()
    assert main(["view", str(valid), "--html", str(page)]) == 0
    assert capfd.readouterr().err == f"wrote {page} (2 plans)\n"


# ----------------------------------------------------------------------------
# plans.json.


def test_plans_json_missing(copy, capfd):
    (copy / "plans.json").unlink()
    assert _one_line(copy, capfd) == (
        f"{str(copy)!r} holds no plans.json (not a results directory; "
        "`mjstamp solve TASK --out DIR` writes one)")


def test_plans_json_truncated_anywhere(copy, capfd):
    full = (copy / "plans.json").read_bytes()
    for cut in _offsets(len(full)):
        (copy / "plans.json").write_bytes(full[:cut])
        message = _one_line(copy, capfd)
        assert message.startswith(f"{str(copy / 'plans.json')!r} is not valid JSON"), cut
        # The task is read off what is left, for the advice, once its name is whole.
        assert message.endswith(_rerun(copy) if cut >= full.index(b'"tiny"') + 6
                                else f"re-run `mjstamp solve TASK --out {copy}`"), cut


@pytest.mark.parametrize("content", [b"", b"\x00\xff\x93NUMPY garbage", b"plans: yes",
                                     b"[" * 100_000])
def test_plans_json_not_json(copy, capfd, content):
    (copy / "plans.json").write_bytes(content)
    assert _one_line(copy, capfd).startswith(f"{str(copy / 'plans.json')!r} is not valid JSON")


def _del(*keys):
    def change(data):
        for k in keys[:-1]:
            data = data[k]
        del data[keys[-1]]
    return change


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def change(data):
        for k in keys[:-1]:
            data = data[k]
        data[keys[-1]] = value
    return change


@pytest.mark.parametrize("change, expected", [
    (_del("plans"), "lacks 'plans'"),
    (_del("task_plans"), "lacks 'task_plans'"),
    (_set("plans", {"0": {}}), "has 'plans' an object, not a list"),
    (_set("plans", 1, 5), "has plans[1] an integer, not an object"),
    (_set("plans", 1, "particle", "1"), "has plans[1].particle a string, not an integer"),
    (_set("plans", 1, "particle", True), "has plans[1].particle true/false, not an integer"),
    (_set("plans", 2, "particle", 1), "has plans[2].particle 1 twice"),
    (_set("plans", 0, "particle", -1), "has plans[0].particle -1 < 0"),
    (_set("plans", 0, "verified", "yes"), "has plans[0].verified a string, not true/false"),
    (_set("plans", 3, "cost", None), "has plans[3].cost null, not a number"),
    (_set("plans", 0, "task_plan", ["1-goal"]), "has plans[0].task_plan a list, not a string"),
    (_del("plans", 2, "cost"), "has no 'cost' in plans[2]"),
    (_set("task_plans", 0, {}), "has no 'task_plan' in task_plans[0]"),
    (_set("task_plans", ["0-goal"]), "has task_plans[0] a string, not an object"),
    (_set("particles", 6.0), "has 'particles' a number, not an integer"),
    (_set("declaration", []), "has 'declaration' a list, not an object"),
    (_set("declaration", "display", "trace", "puck"),
     "has declaration.display.trace that is not a list of body names"),
    (_set("declaration", "display", "force", ["puck", "wall"]),
     "has declaration.display.force that is not a list of [geom, geom] pairs"),
])
def test_plans_json_of_the_wrong_shape(copy, capfd, change, expected):
    data = _json(copy)
    change(data)
    _write_json(copy, data)
    assert _one_line(copy, capfd) == f"{str(copy / 'plans.json')!r} {expected}; {_rerun(copy)}"


@pytest.mark.parametrize("change, expected", [
    (lambda data: [data], "holds a list, not an object with schema_version, task and plans"),
    (lambda data: "plans", "holds a string, not an object with schema_version, task and plans"),
    (_del("task"), "lacks 'task'"),
    (_set("task", 3), "has 'task' an integer, not a string"),
    (lambda data: data | {"task": "tiny; rm -rf ~", "plans": "?"},
     "has 'plans' a string, not a list"),
])
def test_plans_json_of_the_wrong_shape_without_a_task(copy, capfd, change, expected):
    # No task name to suggest (or none fit for a command line): the advice says TASK.
    data = _json(copy)
    changed = change(data)
    _write_json(copy, data if changed is None else changed)
    assert _one_line(copy, capfd) == (
        f"{str(copy / 'plans.json')!r} {expected}; re-run `mjstamp solve TASK --out {copy}`")


def test_plans_json_of_another_schema_version(copy, capfd):
    _write_json(copy, _json(copy) | {"schema_version": 2})
    assert _one_line(copy, capfd) == (
        f"{str(copy / 'plans.json')!r} has schema_version 2; this mjstamp reads "
        f"{results.SCHEMA_VERSION} ({_rerun(copy)})")


def test_plans_of_another_task(valid, capfd):
    assert _one_line(valid, capfd, task="billiards") == (
        f"{str(valid)!r} holds plans of task 'tiny', not 'billiards'")


# ----------------------------------------------------------------------------
# A solve killed before it wrote plans.json.


def _checkpoint(path: Path, **arrays) -> None:
    (path / "plans.json").unlink()
    np.savez(path / "checkpoint.npz", theta=np.zeros((N, 2)), **arrays)


@pytest.mark.parametrize("meta, task", [
    (json.dumps({"task": "tiny", "iteration": 3}), "tiny"),
    (json.dumps({"task": "tiny"}).encode(), "tiny"),  # stored as bytes
    (json.dumps({"iteration": 3}), "TASK"),  # no task in it
    (json.dumps({"task": "rm -rf /; tiny"}), "TASK"),  # not a name to paste into a shell
    ("{not json", "TASK"),
    (None, "TASK"),  # no meta at all
])
def test_unfinished_solve_says_how_to_resume(copy, capfd, meta, task):
    _checkpoint(copy, **({} if meta is None else {"meta": np.array(meta)}))
    assert _one_line(copy, capfd) == (
        f"{str(copy)!r} holds a checkpoint.npz but no plans.json: the solve did not finish; "
        f"`mjstamp solve {task} --resume {copy}` continues it")


def test_unfinished_solve_with_a_damaged_checkpoint(copy, capfd):
    _checkpoint(copy, meta=np.array(json.dumps({"task": "tiny"})))
    full = (copy / "checkpoint.npz").read_bytes()
    for cut in _offsets(len(full), 4):
        (copy / "checkpoint.npz").write_bytes(full[:cut])
        assert f"`mjstamp solve TASK --resume {copy}` continues it" in _one_line(copy, capfd)


def test_unfinished_solve_named_for_another_task(copy, capfd):
    # The checkpoint says which task to resume, whatever --task was given.
    _checkpoint(copy, meta=np.array(json.dumps({"task": "tiny"})))
    assert "`mjstamp solve tiny --resume" in _one_line(copy, capfd, task="billiards")


# ----------------------------------------------------------------------------
# particles.npz, trajectories.npz, scene.mjb: missing, truncated, not what they say.


@pytest.mark.parametrize("name", ["particles.npz", "trajectories.npz", "scene.mjb"])
def test_file_missing(copy, capfd, name):
    (copy / name).unlink()
    assert _one_line(copy, capfd) == (
        f"{str(copy)!r} lacks {name} (an incomplete copy?); {_rerun(copy)}")


def test_everything_but_plans_json_missing(copy, capfd):
    for name in ("particles.npz", "trajectories.npz", "scene.mjb"):
        (copy / name).unlink()
    assert _one_line(copy, capfd).startswith(
        f"{str(copy)!r} lacks particles.npz, trajectories.npz, scene.mjb")


@pytest.mark.parametrize("name", ["particles.npz", "trajectories.npz"])
def test_npz_truncated_anywhere(copy, capfd, name):
    full = (copy / name).read_bytes()
    for cut in _offsets(len(full)):
        (copy / name).write_bytes(full[:cut])
        message = _one_line(copy, capfd)
        assert message.startswith(f"{str(copy / name)!r} is truncated or not an .npz "
                                  "archive ("), cut
        assert message.endswith(_rerun(copy))


@pytest.mark.parametrize("name", ["particles.npz", "trajectories.npz"])
def test_npz_corrupt_inside(copy, capfd, name):
    # Bytes overwritten in the middle: the archive opens, a member fails its CRC
    # or does not inflate.
    data = bytearray((copy / name).read_bytes())
    middle = len(data) // 2
    data[middle : middle + 16] = bytes(16)
    (copy / name).write_bytes(bytes(data))
    message = _one_line(copy, capfd)
    assert message.startswith(f"{str(copy / name)!r} is corrupt (")
    assert message.endswith(_rerun(copy))


@pytest.mark.parametrize("content, expected", [
    (b"not a zip at all", "is truncated or not an .npz archive (ValueError: "),
    (b"PK\x03\x04 a zip header, then nothing", "is truncated or not an .npz archive ("),
    (None, "holds one .npy array, not an .npz archive"),
])
@pytest.mark.parametrize("name", ["particles.npz", "trajectories.npz"])
def test_npz_not_a_zip(copy, capfd, name, content, expected):
    if content is None:
        buffer = io.BytesIO()
        np.save(buffer, np.zeros(3))
        content = buffer.getvalue()
    (copy / name).write_bytes(content)
    assert _one_line(copy, capfd).startswith(f"{str(copy / name)!r} {expected}")


def test_npz_of_pickled_objects(copy, capfd):
    np.savez(copy / "trajectories.npz", particle=np.array([{"a": 1}], dtype=object))
    assert _one_line(copy, capfd).startswith(
        f"{str(copy / 'trajectories.npz')!r} is corrupt (ValueError: Object arrays cannot be "
        "loaded when allow_pickle=False)")


def _drop(*keys):
    def change(arrays):
        for k in keys:
            del arrays[k]
    return change


def _put(key, make):
    def change(arrays):
        arrays[key] = make(arrays[key])
    return change


def _first_rows(n):
    def change(arrays):
        for k in ("particle", "qpos0", "qvel0", "qpos", "qvel", "ctrl", "xpos"):
            arrays[k] = arrays[k][:n]
    return change


def _first_steps(n):
    def change(arrays):
        for k in ("qpos", "qvel", "ctrl", "xpos"):
            arrays[k] = arrays[k][:, :n]
    return change


@pytest.mark.parametrize("change, expected", [
    (_drop("qpos"), "lacks qpos"),
    (_drop("particle", "qpos0"), "lacks particle, qpos0"),
    (_first_rows(3), "has no trajectory of particle 4, which plans.json lists (fewer rows "
                     "than plans?)"),
    (_first_rows(0), "has no trajectory of particle 0, 1, 3, 4, which plans.json lists"),
    (_put("particle", lambda a: a[:3]), "has qpos of shape (4, 40, 2), where rows=3"),
    (_put("particle", lambda a: a.astype(float)), "has particle of dtype float64, not numbers"),
    (_put("particle", lambda a: a.astype(str)), "has particle of dtype <U21, not numbers"),
    (_put("qpos", lambda a: a[:, :, 0]), "has qpos of shape (4, 40), not (rows, T, nq)"),
    (_first_steps(0), "has trajectories of no steps"),
    (_put("qpos0", lambda a: a[:, :1]), "has qpos0 of shape (4, 1), where nq=2"),
    (_put("qvel", lambda a: a[:, :-1]), "has qvel of shape (4, 39, 2), where T=40"),
    (_put("ctrl", lambda a: a[:2]), "has ctrl of shape (2, 40, 0), where rows=4"),
    (_put("xpos", lambda a: a[..., :2]),
     "has xpos of shape (4, 40, 2, 2), not (rows, T, nbody, 3)"),
    (_put("timestep", lambda a: np.array([a, a])), "has timestep of shape (2,), not ()"),
    (_put("timestep", lambda a: np.float64(0)), "has timestep 0.0, not > 0"),
    (_put("timestep", lambda a: np.float64("nan")), "has timestep nan, not > 0"),
])
def test_trajectories_missing_arrays_or_of_the_wrong_shape(copy, capfd, change, expected):
    _rewrite_npz(copy, "trajectories", change)
    message = _one_line(copy, capfd)
    assert message.startswith(f"{str(copy / 'trajectories.npz')!r} {expected}"), message
    assert message.endswith(_rerun(copy))


@pytest.mark.parametrize("change, expected", [
    (_put("theta", lambda a: a[:5]), "has theta of 5 rows, but plans.json has 6 particles"),
    (_put("cost", lambda a: a[:4]), "has cost of 4 rows, but plans.json has 6 particles"),
    (_put("verified", lambda a: np.bool_(True)), "has verified of shape (), not one row"),
])
def test_particles_of_the_wrong_shape(copy, capfd, change, expected):
    _rewrite_npz(copy, "particles", change)
    assert _one_line(copy, capfd).startswith(f"{str(copy / 'particles.npz')!r} {expected}")


def test_particles_fewer_than_the_plans_referenced(copy, capfd):
    # Without a particle count in plans.json the arrays set it; the plans must fit.
    data = _json(copy)
    del data["particles"]
    _write_json(copy, data)
    _rewrite_npz(copy, "particles", lambda arrays: arrays.update(
        {k: arrays[k][:4] for k in results.PER_PARTICLE}))
    assert _one_line(copy, capfd).startswith(
        f"{str(copy / 'particles.npz')!r} has theta of 4 rows, but plans.json has a plan of "
        "particle 4")


def test_scene_mjb_truncated_anywhere(copy, capfd):
    full = (copy / "scene.mjb").read_bytes()
    for cut in _offsets(len(full)):
        (copy / "scene.mjb").write_bytes(full[:cut])
        message = _one_line(copy, capfd)
        # MuJoCo's own reason (its warning, which it would print on stderr) is in the line.
        assert message.startswith(f"{str(copy / 'scene.mjb')!r} is not a readable MuJoCo "
                                  "model ("), cut
        assert cut < 4 or "model file" in message.lower(), message
        assert message.endswith(_rerun(copy))


@pytest.mark.parametrize("content", [b"", b"hello" * 100, (b"\x00" * 4096)])
def test_scene_mjb_not_a_model(copy, capfd, content):
    (copy / "scene.mjb").write_bytes(content)
    assert _one_line(copy, capfd).startswith(
        f"{str(copy / 'scene.mjb')!r} is not a readable MuJoCo model (")


def test_scene_mjb_of_another_scene(copy, capfd, tiny_xml):
    # The wall given a hinge: a scene that loads but is not the one the states are of.
    xml = tiny_xml().replace('<body name="puck">', '<body name="puck">\n'
                             '      <joint name="spin" type="hinge" axis="0 0 1"/>')
    m = mujoco.MjModel.from_xml_string(xml)
    results.save(copy, {k: v for k, v in _json(copy).items() if k != "schema_version"}, {},
               model=m)
    assert _one_line(copy, capfd) == (
        f"{str(copy / 'trajectories.npz')!r} has qpos of shape (4, 40, 2) but scene.mjb has "
        f"nq=3 (files from different runs?); {_rerun(copy)}")


def test_live_view_of_a_damaged_directory_is_one_line_before_any_server(copy, capfd):
    (copy / "plans.json").write_bytes((copy / "plans.json").read_bytes()[:100])
    message = _one_line(copy, capfd)
    assert main(["view", str(copy), "--no-browser"]) == 2
    assert capfd.readouterr().err == f"mjstamp: error: {message}\n"
    assert not (copy / "plans.html").exists()  # no fallback page: nothing to play
