"""MJX against MuJoCo C on a scene: where rollouts part, which pairs, and C's own chaos.

A crate tossed onto the floor (plane-box contacts, MuJoCo's defaults): with
MJX's own plane-box function the rollouts part from C at the first contact,
and `fidelity.judge` must name the pair; with C's routine ported
(`mjstamp.colliders`) they agree to rounding.
"""

import numpy as np
import pytest

from mjstamp import colliders, verify
from mjstamp.scenes import Scene, fidelity
from mjstamp.scenes.rollout import replay

DROP = """
<mujoco model="drop">
  <option timestep="0.01"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="crate" pos="0 0 0.3">
      <freejoint/>
      <geom name="crate" type="box" size="0.1 0.07 0.05" mass="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""
HORIZON = 60


def _tosses(scene, n=16):
    rng = np.random.default_rng(0)
    qpos0 = np.tile(scene.m.qpos0, (n, 1))
    qvel0 = np.zeros((n, scene.m.nv))
    qvel0[:, :3] = rng.uniform(-1, 1, (n, 3))
    qvel0[:, 3:] = rng.uniform(-6, 6, (n, 3))
    return qpos0, qvel0


def _judge(scene, qpos0, qvel0):
    # N.B. the converged solver: only the contacts can tell MJX from C here.
    q = np.asarray(scene.rollout_fn(HORIZON, fields=("qpos",))(qpos0, qvel0)["qpos"])
    qc = replay(scene, qpos0, qvel0, horizon=HORIZON, fields=("qpos",))["qpos"]
    return fidelity.judge(scene, qpos0, qvel0, None, q, qc,
                          tolerance=fidelity.default_tolerance(scene), horizon=HORIZON)


@pytest.mark.slow
def test_ported_plane_box_follows_c_and_mjx_own_parts_at_the_named_pair():
    scene = Scene(DROP, gradient="implicit", iterations=100)
    qpos0, qvel0 = _tosses(scene)
    ported = _judge(scene, qpos0, qvel0)
    assert ported.judged_by == "tolerance" and ported.p95_m < 1e-10  # rounding: 1e-14 seen
    assert ported.approximate == ()
    own_scene = Scene(DROP, gradient="implicit", iterations=100)
    with colliders.mjx_own():
        own = _judge(own_scene, qpos0, qvel0)
        msg = own.message("drop", scene.m, HORIZON)
    # MJX's own plane-box parts from C by centimetres (0.08 m seen).
    assert own.judged_by == "none" and own.p95_m > 100 * own.tolerance_m
    floor, crate = scene.geom("floor"), scene.geom("crate")
    assert list(own.parting.pairs) == [(floor, crate)]
    assert own.parting.pairs[(floor, crate)] == own.parting.particles > 0
    assert own.approximate == ((floor, crate),)
    assert "\n" not in msg
    assert "they part at contacts of plane-box 'floor'/'crate'" in msg
    assert "MJX collides these pairs differently from C: plane-box 'floor'/'crate'" in msg


def test_judge_by_chaos_and_its_must_fail_case():
    """C nudged by less than NUDGE_M is within C's own spread; a real parting is not."""
    scene = Scene(DROP)
    qpos0, qvel0 = _tosses(scene, n=8)
    qc = replay(scene, qpos0, qvel0, horizon=HORIZON, fields=("qpos",))["qpos"]
    near = replay(scene, qpos0 + 1e-11, qvel0, horizon=HORIZON, fields=("qpos",))["qpos"]
    tiny = 1e-14  # below the 1e-11 m nudge's divergence: the tolerance alone would reject
    v = fidelity.judge(scene, qpos0, qvel0, None, near, qc, tolerance=tiny, horizon=HORIZON)
    assert v.judged_by == "chaos" and v.faithful and v.p95_m > tiny
    assert v.p95_m <= v.chaos_p95_m
    assert "within the scene's own chaos" in v.message("drop", scene.m, HORIZON)
    far = qc.copy()
    far[:, 30:, 2] += 1e-3  # the crate jumps a millimetre at step 31
    v = fidelity.judge(scene, qpos0, qvel0, None, far, qc, tolerance=1e-4, horizon=HORIZON)
    assert v.judged_by == "none" and not v.faithful
    assert set(v.parting.steps) == {31}
    assert v.parting.particles == 8


def test_chaos_spread_is_zero_without_a_nudge():
    scene = Scene(DROP)
    qpos0, qvel0 = _tosses(scene, n=4)
    assert (fidelity.chaos_spread(scene, qpos0, qvel0, horizon=10, nudge=0.0) == 0).all()
    assert (fidelity.chaos_spread(scene, qpos0, qvel0, horizon=10) > 0).all()


def test_solve_warns_in_one_line_and_goes_on_where_mjx_parts(monkeypatch, tiny_task):
    """A parting MJX is a FidelityWarning naming the pairs, not a refusal."""
    import warnings

    from mjstamp.errors import FidelityWarning
    from mjstamp.solver import pipeline as solve_mod

    problem = tiny_task().build()
    theta = np.array([[1.0, 0.5], [1.5, -0.5]])
    replay_c = verify.simulate_c(problem, theta)
    off = replay_c.qpos.copy()
    off[:, 10:, 0] += 0.05  # the puck jumps 5 cm at step 11

    class Evaluate:
        def mjx(self, th):
            return np.zeros(len(th)), off

    class Calibration:
        tolerance_m = 1e-3

    said = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report = solve_mod._check_mjx(problem, Evaluate(), theta, Calibration(), said.append,
                                      replay_c)
    (w,) = [w for w in caught if issubclass(w.category, FidelityWarning)]
    msg = str(w.message)
    assert "\n" not in msg and msg.startswith("scene 'tiny': MJX rollouts vs MuJoCo C")
    assert "planning anyway: every plan is verified and repaired in MuJoCo C" in msg
    assert report["mjx_initial"]["judged_by"] == "none"
    assert report["mjx_initial"]["parting"]["particles"] == 2
    assert report["mjx_initial_divergence_p95_m"] == pytest.approx(0.05, rel=1e-6)
