"""mjstamp.svgd runs on any log density: it imports neither MuJoCo nor mjstamp.relax."""

import ast
import pathlib
import subprocess
import sys

SVGD = pathlib.Path(__file__).resolve().parents[1] / "mjstamp" / "svgd"
# What mjstamp/svgd/__init__.py says the engine may import, besides the standard library.
ALLOWED = {"jax", "numpy", "optax", "tqdm"}


def _imported_modules(path: pathlib.Path) -> set[str]:
    """Every module a file imports, at the top or inside a function (absolute names)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module)
    return out


def test_every_svgd_file_imports_only_the_stdlib_jax_numpy_optax_tqdm_errors_and_itself():
    files = sorted(SVGD.glob("*.py"))
    assert {f.name for f in files} >= {"__init__.py", "kernels.py", "stamp.py", "steps.py"}
    for path in files:
        for module in _imported_modules(path):
            top = module.split(".")[0]
            ok = (
                top in sys.stdlib_module_names
                or top in ALLOWED
                or module == "mjstamp.svgd"
                or module == "mjstamp.progress"
                or module == "mjstamp.errors"  # a leaf: the exception type users catch
                or module.startswith("mjstamp.svgd.")
            )
            assert ok, f"{path.name} imports {module}"


def test_the_progress_reporter_the_engine_may_use_imports_only_the_stdlib():
    path = SVGD.parent / "progress.py"
    assert all(m.split(".")[0] in sys.stdlib_module_names or m == "__future__"
               for m in _imported_modules(path)), _imported_modules(path)


def test_importing_svgd_loads_neither_mujoco_nor_relax():
    """In a fresh interpreter: what the import of mjstamp.svgd pulls in, transitively."""
    code = (
        "import sys, mjstamp.svgd\n"
        "bad = [m for m in sys.modules if m.split('.')[0] == 'mujoco'"
        " or m == 'mjstamp.relax' or m.startswith('mjstamp.relax.')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_scanner_sees_top_level_and_lazy_imports(tmp_path):
    """A check is only as good as the case where it must fail: it sees both kinds."""
    bad = tmp_path / "bad.py"
    bad.write_text("import jax\n\ndef f():\n    from mjstamp.relax import soft_onehot\n"
                   "    import mujoco.mjx\n")
    assert _imported_modules(bad) == {"jax", "mjstamp.relax", "mujoco.mjx"}
