"""`Scene.menagerie`: MuJoCo Menagerie robots by name, through the `mujoco_menagerie` package.

No test touches the network: the package is made absent (its import fails), or a
fake one is installed in tmp_path with the real package's API as far as the loader
uses it (`get`, `names`, `Cache` with `MENAGERIE_CACHE_DIR`, `Robot.xml`,
`Cache.is_cached`, `UnknownRobotError` with `suggestions`, `DownloadError`) and a
cache laid out as the real one (`models/<name>-<oid16>/.complete`), holding a small
MJCF that reads a mesh from its `meshdir`. Its "download" fails as it does offline.
"""

import sys
import textwrap

import pytest

from mjstamp.errors import MjstampError
from mjstamp.scenes import Scene, menagerie_model_path

FAKE = '''
import dataclasses, difflib, os, pathlib

class MenagerieError(Exception):
    pass

class DownloadError(MenagerieError):
    pass

class UnknownRobotError(MenagerieError, LookupError):
    def __init__(self, name, known):
        self.suggestions = difflib.get_close_matches(name, list(known), n=3)
        super().__init__(f"Unknown robot {name!r}.")

class Cache:
    def __init__(self, dir=None, base_url=None, root=None):
        self.dir = pathlib.Path(dir or os.environ["MENAGERIE_CACHE_DIR"])
        self.root = root or os.environ.get("MENAGERIE_ROOT")

    def model_path(self, robot):
        return self.dir / "models" / f"{robot.name}-{robot.oid[:16]}"

    def is_cached(self, robot):
        return (self.model_path(robot) / ".complete").is_file()

    def resolve(self, robot, progress=None):
        if self.is_cached(robot):
            return self.model_path(robot)
        DOWNLOADS.append(robot.name)
        raise DownloadError(f"https://example.invalid/{robot.name}.tar.xz: <urlopen error "
                            "[Errno -3] Temporary failure in name resolution>")

@dataclasses.dataclass(frozen=True)
class Robot:
    name: str
    oid: str
    entries: dict
    default_scene: str = "scene"

    @property
    def entry_names(self):
        return tuple(self.entries)

    def path(self, cache=None, progress=None):
        return (cache or Cache()).resolve(self, progress)

    def xml(self, entry=None, cache=None):
        return self.path(cache) / self.entries[entry or self.default_scene]

ROBOTS = {r.name: r for r in (
    Robot("acme_arm", "0123456789abcdef0123", {"scene": "scene.xml", "arm": "arm.xml"}),
    Robot("acme_hand", "fedcba98765432100000", {"scene": "scene.xml"}),
    *(Robot(f"zz_robot_{k}", f"{k:020d}", {"scene": "scene.xml"}) for k in range(8)),
)}
DOWNLOADS = []

def names():
    return sorted(ROBOTS)

def get(name):
    if name not in ROBOTS:
        raise UnknownRobotError(name, ROBOTS)
    return ROBOTS[name]
'''

ARM = """
<mujoco model="acme arm">
  <compiler meshdir="assets"/>
  <asset><mesh name="tet" file="tet.obj"/></asset>
  <worldbody>
    <body name="link" pos="0 0 0.2">
      <joint name="shoulder" type="hinge" axis="0 0 1"/>
      <geom name="link" type="mesh" mesh="tet"/>
    </body>
  </worldbody>
  <actuator><motor name="shoulder" joint="shoulder"/></actuator>
</mujoco>
"""
SCENE = """
<mujoco model="acme arm scene">
  <include file="arm.xml"/>
  <worldbody><geom name="floor" type="plane" size="1 1 0.1"/></worldbody>
</mujoco>
"""
TET = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


@pytest.fixture
def fake_menagerie(tmp_path, monkeypatch):
    """The fake package on sys.path, its cache holding acme_arm (not acme_hand)."""
    package = tmp_path / "site" / "mujoco_menagerie"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(textwrap.dedent(FAKE))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.delitem(sys.modules, "mujoco_menagerie", raising=False)
    cache = tmp_path / "cache"
    monkeypatch.setenv("MENAGERIE_CACHE_DIR", str(cache))
    monkeypatch.delenv("MENAGERIE_ROOT", raising=False)
    model = cache / "models" / "acme_arm-0123456789abcdef"
    (model / "assets").mkdir(parents=True)
    (model / "assets" / "tet.obj").write_text(TET)
    (model / "arm.xml").write_text(ARM)
    (model / "scene.xml").write_text(SCENE)
    (model / ".complete").write_text("{}")
    import mujoco_menagerie

    yield mujoco_menagerie, cache
    monkeypatch.delitem(sys.modules, "mujoco_menagerie", raising=False)


def test_cached_robot_loads_by_name_with_its_assets(fake_menagerie):
    mm, cache = fake_menagerie
    scene = Scene.menagerie("acme_arm")  # the default scene: floor + arm, mesh from meshdir
    assert scene.name == "acme_arm"
    assert (scene.m.nmesh, scene.m.nu, scene.m.ngeom) == (1, 1, 2)
    assert scene.actuator("shoulder") == 0
    arm = Scene.menagerie("acme_arm", "arm", name="arm", ls_iterations=2)  # an entry point
    assert (arm.name, arm.m.ngeom, arm.grad_options.ls_iterations) == ("arm", 1, 2)
    assert menagerie_model_path("acme_arm", download=False) == (
        cache / "models" / "acme_arm-0123456789abcdef" / "scene.xml")
    assert mm.DOWNLOADS == []


def test_package_not_installed(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco_menagerie", None)  # import fails
    with pytest.raises(MjstampError) as e:
        Scene.menagerie("franka_emika_panda")
    assert str(e.value) == (
        "menagerie robot 'franka_emika_panda': the mujoco_menagerie package is not "
        "installed; run `pip install mujoco-menagerie` (it downloads each robot on first "
        "use, or ahead with `mujoco-menagerie prefetch franka_emika_panda`)")


def test_unknown_robot_and_entry_point(fake_menagerie):
    with pytest.raises(MjstampError) as e:
        Scene.menagerie("acme_armm")
    assert str(e.value) == (
        "unknown menagerie robot 'acme_armm'; did you mean 'acme_arm'? valid: acme_arm, "
        "acme_hand, zz_robot_0, zz_robot_1, zz_robot_2, zz_robot_3, ... (10 in all; "
        "`mujoco-menagerie names` lists them)")
    with pytest.raises(MjstampError) as e:
        Scene.menagerie("acme_arm", "mjx_scene")
    assert str(e.value) == (
        "menagerie robot 'acme_arm' has no entry point 'mjx_scene'; valid: scene, arm")


def test_not_cached_and_no_network(fake_menagerie):
    mm, cache = fake_menagerie
    with pytest.raises(MjstampError) as e:
        Scene.menagerie("acme_hand", download=False)
    assert str(e.value) == (
        f"menagerie robot 'acme_hand' is not in the menagerie cache ({cache}) and "
        "download=False; run `mujoco-menagerie prefetch acme_hand` where there is network, "
        "or set MENAGERIE_CACHE_DIR to a cache that holds it")
    assert mm.DOWNLOADS == []  # download=False never tries
    with pytest.raises(MjstampError) as e:
        Scene.menagerie("acme_hand")
    assert mm.DOWNLOADS == ["acme_hand"]
    assert "\n" not in str(e.value)
    assert str(e.value) == (
        f"menagerie robot 'acme_hand' is not in the menagerie cache ({cache}) and could not "
        "be downloaded (https://example.invalid/acme_hand.tar.xz: <urlopen error [Errno -3] "
        "Temporary failure in name resolution>); run `mujoco-menagerie prefetch acme_hand` "
        "where there is network, or set MENAGERIE_CACHE_DIR to a cache that holds it")
