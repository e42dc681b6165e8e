"""Scene construction, names, options, and the one-line errors of bad input."""

import mujoco
import pytest
from dm_control import mjcf

from mjstamp.errors import MjstampError
from mjstamp.scenes import GradOptions, Scene, package_model_path, shipped_models

BALL = """
<mujoco model="ball">
  <worldbody>
    <body name="ball"><joint name="x" type="slide" axis="1 0 0"/>
      <geom name="ball" type="sphere" size="0.1"/></body>
  </worldbody>
</mujoco>
"""


def test_shipped_models_are_package_data(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # found whatever the current directory
    assert {"billiards", "pushing"} <= set(shipped_models())
    assert package_model_path("billiards.xml").is_file()


def test_scene_from_path_string_and_mjcf_element(tmp_path):
    path = tmp_path / "ball.xml"
    path.write_text(BALL)
    root = mjcf.from_xml_string(BALL)
    for source in (path, str(path), BALL, root):
        scene = Scene(source)
        assert scene.m.nq == 1
        assert scene.geom("ball") == 0
        assert scene.mx.opt.iterations == 1


def test_mjcf_composition_through_dm_control():
    arena = mjcf.RootElement(model="arena")
    arena.worldbody.add("geom", name="floor", type="plane", size=[1, 1, 0.1])
    ball = mjcf.from_xml_string(BALL)
    arena.attach(ball)
    scene = Scene(arena)
    assert "ball/ball" in scene.names("geom")
    assert scene.qpos_adr("ball/x") == 0


def test_names_resolved_once_with_valid_list(billiards):
    assert billiards.body("cue") == mujoco.mj_name2id(
        billiards.m, mujoco.mjtObj.mjOBJ_BODY, "cue"
    )
    for kind in ("body", "geom", "joint", "site"):
        with pytest.raises(MjstampError) as e:
            billiards.id(kind, "nope")
        msg = str(e.value)
        assert "\n" not in msg and "'nope'" in msg and "valid:" in msg
    with pytest.raises(MjstampError, match="valid: world, cue, target"):
        billiards.body("cue_ball")


def test_gradient_options_leave_scene_options_alone(billiards):
    assert billiards.m.opt.iterations == 100  # the MJCF's own (MuJoCo default)
    assert billiards.m_grad.opt.iterations == 1
    assert billiards.m_grad.opt.ls_iterations == GradOptions().ls_iterations
    assert billiards.m_grad.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON


def test_options_overridden_by_mjcf_then_caller():
    xml = BALL.replace(
        "<worldbody>",
        '<custom><numeric name="mjstamp.grad.ls_iterations" data="7"/></custom>'
        "<worldbody>",
    )
    assert Scene(xml).m_grad.opt.ls_iterations == 7
    assert Scene(xml, ls_iterations=2).m_grad.opt.ls_iterations == 2
    assert Scene(xml, timestep=0.005).m_grad.opt.timestep == 0.005
    assert Scene(BALL, iterations=3).m_grad.opt.iterations == 3
    with pytest.raises(MjstampError, match="iterations=0"):
        Scene(BALL, iterations=0)
    with pytest.raises(MjstampError, match="unknown option 'lsiter'"):
        Scene(BALL, lsiter=3)
    bad = BALL.replace(
        "<worldbody>",
        '<custom><numeric name="mjstamp.grad.bogus" data="7"/></custom><worldbody>',
    )
    with pytest.raises(MjstampError, match="mjstamp.grad.bogus"):
        Scene(bad)


def test_precision_must_follow_x64_flag():
    with pytest.raises(MjstampError, match="jax_enable_x64"):
        Scene(BALL, precision="float32")  # the test session runs float64


@pytest.mark.parametrize(
    "xml, expected",
    [
        ("<mujoco><worldbody><body><geom type='sphere'/></body></worldbody>", "XML"),
        (
            "<mujoco><asset><mesh name='m' file='missing.stl'/></asset>"
            "<worldbody><geom type='mesh' mesh='m'/></worldbody></mujoco>",
            "missing.stl",
        ),
        ("<mujoco><include file='other.xml'/></mujoco>", "other.xml"),
    ],
    ids=["malformed", "missing-mesh", "missing-include"],
)
def test_bad_mjcf_is_one_line_naming_the_file(tmp_path, xml, expected):
    path = tmp_path / "scene.xml"
    path.write_text(xml)
    with pytest.raises(MjstampError) as e:
        Scene(path)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(path) in msg and expected in msg


def test_missing_file_and_unknown_shipped_scene(tmp_path):
    with pytest.raises(MjstampError, match="not found"):
        Scene(tmp_path / "nope.xml")
    with pytest.raises(MjstampError, match="unknown scene 'nope'; valid: billiards"):
        Scene.shipped("nope")
