"""Rollout gradients through a pair `ccd.ccd_converged` differentiates, against MuJoCo C.

The per-pair tests (test_contacts_convex.py) check one collision's
derivatives; a rollout chains hundreds of them through the solver. Here a
convex mesh rock dropped on a box (box-mesh, C's GJK/EPA, exact meshes) goes
through `check_scene`: reverse-mode AD of a smooth function of the MJX
rollout against central differences of the same function in float64 MuJoCo C.

N.B. one scene per family is in benchmarks/perf/rollout_gradients.py: a
cylinder or ellipsoid pair (`ccd.ccd`, AD through every GJK/EPA iteration)
takes minutes and gigabytes to compile in a rollout. The issue's cylinder
puck ("AD against central differences 0.93") was MuJoCo C's own
plane-cylinder contacts, which are not smooth at the difference step; `check`
now reports that (`fd_smooth_particles`; the last test here).
"""

import pathlib
import sys

import mujoco
import pytest

from mjstamp import colliders
from mjstamp.scenes import Scene
from mjstamp.scenes.check import check_scene

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks.perf import rollout_gradients  # noqa: E402 - after the path set-up above


@pytest.fixture()
def exact_meshes():
    colliders.patch_collisions()
    colliders.exact_meshes()
    yield
    colliders.exact_meshes(False)


def test_the_rock_meets_the_box():
    xml, spec = rollout_gradients.scenes()["rock_on_box"]
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    met = set()
    for _ in range(spec.horizon):
        mujoco.mj_step(m, d)
        met |= {tuple(int(m.geom_type[g]) for g in c.geom) for c in d.contact[: d.ncon]}
    assert (int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_MESH)) in met


@pytest.mark.slow
def test_rollout_gradients_through_a_converged_pair_are_those_of_c(exact_meshes):
    """AD of MJX rollouts against C's central differences within 1e-4 (median relative error)."""
    xml, spec = rollout_gradients.scenes()["rock_on_box"]
    scene = Scene(xml, name="rock_on_box").with_grad_options(
        gradient="implicit", iterations=100, warmstart=False)
    report = check_scene(scene, particles=8, spec=spec, calibrate=False)
    assert report["faithful"] and report["approximate_pairs"] == [], report
    assert report["nonfinite"] == 0
    assert report["fd_smooth_particles"] >= 6, report  # 8 of 8 seen
    assert report["rel_err_median"] <= 1e-4, report  # 1.4e-9 seen


@pytest.mark.slow
@pytest.mark.parametrize("puck", ["puck_cylinder", "puck_box"])
def test_check_judges_gradients_only_where_c_is_smooth(puck):
    """A cylinder puck on a table: C's differences at 1e-6 and 1e-5 disagree on every particle."""
    xml, spec = rollout_gradients.scenes()[puck]
    scene = Scene(xml, name=puck).with_grad_options(
        gradient="implicit", iterations=100, warmstart=False)
    report = check_scene(scene, particles=8, spec=spec, calibrate=False)
    assert report["faithful"], report
    if puck == "puck_cylinder":
        assert report["fd_smooth_particles"] == 0 and not report["healthy"], report
        assert report["rel_err_median"] is None
        assert any("not smooth" in p for p in report["problems"]), report["problems"]
    else:
        assert report["fd_smooth_particles"] >= 6 and report["healthy"], report  # 7 of 8 seen
        assert report["rel_err_median"] <= 1e-4, report
