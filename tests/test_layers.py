"""The layers docs/architecture.md draws are the imports: a back-arrow fails the suite.

The test reads the `layers` block of docs/architecture.md (top layer first)
and every import of every file under mjstamp/, at the top or inside a
function (`if TYPE_CHECKING:` blocks aside). A module may import modules of
the layers below its own and of its own package, never a layer above or a
neighbour in its own layer.
"""

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mjstamp"
DOC = ROOT / "docs" / "architecture.md"
# Old paths kept for one release: each aliases its new module (mjstamp._moved).
STUBS = {"mjstamp.solve", "mjstamp.scenes.contacts", "mjstamp.scenes.distance"}
# Names of the public face (mjstamp/__init__.py), not modules, when imported from mjstamp.
FACE = {"Scene", "SolveConfig", "Task", "configure", "costs", "load", "solve", "DEFAULT_CACHE"}


def read_layers(text: str) -> list[list[str]]:
    """The `layers` block of architecture.md: one list of names per layer, top first."""
    block = re.search(r"```layers\n(.*?)```", text, re.S)
    assert block, "docs/architecture.md has no ```layers block"
    return [line.split() for line in block.group(1).splitlines() if line.strip()]


def module_name(path: pathlib.Path, root: pathlib.Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports(path: pathlib.Path, root: pathlib.Path = ROOT) -> set[str]:
    """The mjstamp modules a file imports, wherever the import stands.

    `from mjstamp import x` is the module x where there is one, else the face.
    """
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
            and _is_type_checking(node) for n in ast.walk(node)}
    package = root / "mjstamp"
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "mjstamp"}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] != "mjstamp":
                continue
            for a in node.names:
                sub = pathlib.Path(*node.module.split(".")[1:], a.name)
                is_module = (package / sub).with_suffix(".py").exists() or (package / sub).is_dir()
                if node.module == "mjstamp" and (a.name in FACE or not is_module):
                    out.add("mjstamp")
                elif is_module:
                    out.add(f"{node.module}.{a.name}")
                else:
                    out.add(node.module)
    return out


def layer_of(module: str, layers: list[list[str]]) -> tuple[int, str] | None:
    """(layer index counted from the bottom, the layer name that holds `module`)."""
    best = None
    for depth, names in enumerate(reversed(layers)):
        for name in names:
            full = "mjstamp" if name == "mjstamp" else f"mjstamp.{name}"
            if name == "mjstamp" and module != "mjstamp":
                continue
            if (module == full or module.startswith(full + ".")) and (
                    best is None or len(full) > len(best[2])):
                best = (depth, name, full)
    return None if best is None else best[:2]


def back_arrows(root: pathlib.Path, layers: list[list[str]]) -> list[str]:
    """Every import that goes up a layer or sideways within one; files no layer holds."""
    bad = []
    for path in sorted((root / "mjstamp").rglob("*.py")):
        me = module_name(path, root)
        if me in STUBS:
            continue
        mine = layer_of(me, layers)
        if mine is None:
            bad.append(f"{me}: in no layer of docs/architecture.md")
            continue
        for other in sorted(imports(path, root)):
            if other in STUBS:
                bad.append(f"{me} imports {other}, an old path: import where it moved")
                continue
            theirs = layer_of(other, layers)
            if theirs is None or theirs[1] == mine[1]:
                continue  # its own package (a missing file fails where it is imported)
            if theirs[0] >= mine[0]:
                where = "a layer above" if theirs[0] > mine[0] else "its own layer"
                bad.append(f"{me} ({mine[1]}) imports {other} ({theirs[1]}), {where}")
    return bad


def test_every_module_imports_only_the_layers_below_it():
    layers = read_layers(DOC.read_text(encoding="utf-8"))
    assert back_arrows(ROOT, layers) == []


def test_every_name_in_the_picture_is_a_module_and_every_module_is_in_it():
    layers = read_layers(DOC.read_text(encoding="utf-8"))
    names = [n for layer in layers for n in layer]
    assert len(names) == len(set(names)), names
    for name in names:
        if name != "mjstamp":
            path = PACKAGE.joinpath(*name.split("."))
            assert path.with_suffix(".py").exists() or path.is_dir(), name
    tops = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
            if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").exists()}
    assert tops - {"solve"} <= set(names), sorted(tops - set(names))


def test_the_check_finds_a_back_arrow_and_a_sideways_one(tmp_path):
    """A check is only as good as the case where it must fail."""
    pkg = tmp_path / "mjstamp"
    for name in ("low", "mid", "peer", "high"):
        (pkg / name).mkdir(parents=True)
        (pkg / name / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "low" / "a.py").write_text("def f():\n    from mjstamp.high import x\n")
    (pkg / "mid" / "b.py").write_text("from mjstamp import peer\nfrom mjstamp.low import a\n")
    (pkg / "high" / "c.py").write_text(
        "from typing import TYPE_CHECKING\nfrom mjstamp.mid import b\n"
        "if TYPE_CHECKING:\n    from mjstamp import high\n")
    layers = read_layers("```layers\nhigh\nmid peer\nlow\n```")
    assert sorted(back_arrows(tmp_path, layers)) == [
        "mjstamp.low.a (low) imports mjstamp.high (high), a layer above",
        "mjstamp.mid.b (mid) imports mjstamp.peer (peer), its own layer",
        "mjstamp: in no layer of docs/architecture.md",
    ]


def test_a_picture_without_a_layers_block_is_refused():
    with pytest.raises(AssertionError, match="no ```layers block"):
        read_layers("a picture in words only")
