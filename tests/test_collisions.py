"""MJX's refusals, caught up front as one line (mjstamp.scenes.collisions).

Each refused model is also handed to MJX itself, which must refuse it: the
check may not turn away a model MJX builds, nor let through one it does not.
"""

import mujoco
import pytest

from mjstamp._mjx import mjx
from mjstamp.errors import MjstampError
from mjstamp.scenes import Scene
from mjstamp.scenes.collisions import check_collidable

# A cylinder puck sliding between rails of rough ground (height fields): neither
# MJX 3.17 nor mjstamp's ports of MuJoCo C's colliders collide hfield-cylinder
# (C does, by its general convex routine per height-field prism).
# {puck} and {extra} are filled in per test.
_TABLE = """
<mujoco model="rails">
  {option}
  <asset><hfield name="rough" nrow="3" ncol="3" size="1 0.05 0.05 0.01"
                 elevation="0 1 0 1 0 1 0 1 0"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <geom name="rail_left" type="hfield" hfield="rough" pos="0 0.5 0"/>
    <geom name="rail_right" type="hfield" hfield="rough" pos="0 -0.5 0"/>
    <body name="puck" pos="0 0 0.03">
      <freejoint/>
      <geom name="puck" type="cylinder" size="0.1 0.02" {puck}/>
    </body>
  </worldbody>
  {extra}
</mujoco>
"""


def _table(*, puck: str = "", extra: str = "", option: str = "") -> str:
    return _TABLE.format(puck=puck, extra=extra, option=option)


def _mjx_refuses(xml: str) -> bool:
    """Whether MJX itself refuses the model (put_model, or make_data after it)."""
    m = mujoco.MjModel.from_xml_string(xml)
    try:
        mjx.put_model(m)
        mjx.make_data(m)
    except NotImplementedError:
        return True
    return False


def test_cylinder_puck_on_height_field_rails_is_one_line(tmp_path):
    """The rail-puck pair: one line naming both geoms, types, file and fixes."""
    path = tmp_path / "rails.xml"
    path.write_text(_table())
    assert _mjx_refuses(path.read_text())
    with pytest.raises(MjstampError) as e:
        Scene(path)
    msg = str(e.value)
    assert "\n" not in msg
    assert e.value.__cause__ is None and e.value.__context__ is None  # no MJX traceback
    assert msg.startswith(
        f"{path}: geom 'rail_left' (hfield) and geom 'puck' (cylinder) collide in this "
        "model, but hfield-cylinder is not collided by MJX 3.17 or mjstamp's ports of "
        "MuJoCo C's colliders; they collide hfield with: sphere, capsule, box, mesh; and "
        "cylinder with: plane, sphere, capsule, "
    )
    assert "; make geom 'puck' a sphere, capsule, box or mesh" in msg
    assert msg.endswith(
        "or exclude the pair (contype/conaffinity bits, or an <exclude> of their bodies)"
    )


def test_ported_pairs_are_collided():
    """cylinder-box, which MJX 3.17 lacks, builds: MuJoCo C's routine is ported."""
    xml = _table().replace('type="hfield" hfield="rough"', 'type="box" size="1 0.05 0.05"')
    from mjstamp import colliders

    assert (5, 6) in colliders.PORTED
    assert Scene(xml).m.ngeom == 4


def test_cli_prints_the_line_and_exits_2(tmp_path, capsys):
    """`mjstamp check` on the rails: the one line on stderr, status 2."""
    from mjstamp.cli import main

    path = tmp_path / "rails.xml"
    path.write_text(_table())
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"mjstamp: error: {path}: geom 'rail_left' "
                                               "(hfield) and geom 'puck' (cylinder)")


@pytest.mark.parametrize(
    ("puck", "extra"),
    [
        # The puck collides with the floor only: bit 2 is the floor's.
        ('contype="2" conaffinity="2"', ""),
        # The rails are static (world body): excluding world-puck drops them,
        # and with them the floor, which MJX would collide (plane-cylinder).
        ("", '<contact><exclude body1="world" body2="puck"/></contact>'),
    ],
)
def test_excluded_pair_builds(puck, extra):
    """Excluding the pair (contype/conaffinity or <exclude>) builds fine."""
    xml = _table(puck=puck, extra=extra)
    if puck:
        floor = 'name="floor" type="plane"'
        xml = xml.replace(floor, floor + ' contype="2" conaffinity="2"')
    assert not _mjx_refuses(xml)
    scene = Scene(xml)
    assert scene.m.ngeom == 4


def test_explicit_pair_says_remove_it():
    """An explicit <pair> collides whatever the bits say; the fix is to drop it."""
    xml = _table(
        puck='contype="0" conaffinity="0"',
        extra='<contact><pair geom1="puck" geom2="rail_right"/></contact>',
    )
    assert _mjx_refuses(xml)
    with pytest.raises(MjstampError, match=r"^MJCF string: geom 'rail_right' \(hfield\) and "
                       r"geom 'puck' \(cylinder\) collide .* or remove their <pair>$"):  # fmt: skip
        Scene(xml)


def test_unnamed_geoms_by_id():
    """Geoms without names are named by their ids."""
    xml = _table().replace(' name="rail_left"', "").replace(' name="puck" type', " type")
    m = mujoco.MjModel.from_xml_string(xml)
    with pytest.raises(MjstampError, match=r"^x\.xml: geom #1 \(hfield\) and geom #3 \(cylinder\)"):
        check_collidable(m, "x.xml")


_MESH = '<asset><mesh name="tet" vertex="0 0 0  .1 0 0  0 .1 0  0 0 .1"/></asset>'

# Models MJX refuses, and a fragment of the one line that says why.
REFUSED = {
    "implicit integrator": (
        _table(puck='contype="0" conaffinity="0"', option='<option integrator="implicit"/>'),
        "<option integrator='implicit'> is not supported by MJX 3.17; valid: Euler, RK4, "
        "implicitfast",
    ),
    "energy flag": (
        _table(puck='contype="0" conaffinity="0"',
               option='<option><flag energy="enable"/></option>'),
        '<option><flag energy="enable"/> is not supported by MJX 3.17',
    ),
    "fluid with implicitfast": (
        _table(puck='contype="0" conaffinity="0"',
               option='<option integrator="implicitfast" density="1.2"/>'),
        "fluid forces (density, viscosity or wind) with integrator 'implicitfast'",
    ),
    "mesh margin": (
        _table(puck='type="mesh" mesh="tet" margin="0.01"', extra=_MESH).replace(
            'type="cylinder" size="0.1 0.02" ', ""
        ),
        "geom 'puck' (mesh) collide with margin 0.01, but MJX 3.17 has no margin on mesh",
    ),
    "elliptic condim 1": (
        _table(puck='type="sphere"',
               option='<option cone="elliptic"/><default><geom condim="1"/></default>')
        .replace('type="cylinder" size="0.1 0.02" ', 'size="0.1" '),
        "make condim=1 contacts, which MJX 3.17 does not support with <option cone=\"elliptic\">",
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", REFUSED)
def test_other_refusals_are_one_line(case):
    """Options and features MJX refuses: one line, before MJX is reached."""
    xml, fragment = REFUSED[case]
    assert _mjx_refuses(xml)
    with pytest.raises(MjstampError) as e:
        Scene(xml)
    assert fragment in str(e.value) and "\n" not in str(e.value)
    assert str(e.value).startswith("MJCF string: ")


def test_pgs_solver_builds():
    """PGS is refused by MJX, but a Scene hands MJX its GradOptions solver."""
    xml = _table(puck='contype="0" conaffinity="0"', option='<option solver="PGS"/>')
    assert _mjx_refuses(xml)
    m = mujoco.MjModel.from_xml_string(xml)
    check_collidable(m, "pgs.xml")
    assert Scene(xml).m.opt.solver == mujoco.mjtSolver.mjSOL_PGS  # verified in C with it


def test_shipped_scenes_pass():
    """The shipped scenes build under MJX, so the check lets them through."""
    for name in ("billiards", "pushing"):
        from mjstamp.scenes.scene import package_model_path

        m = mujoco.MjModel.from_xml_path(str(package_model_path(f"{name}.xml")))
        check_collidable(m, name)
