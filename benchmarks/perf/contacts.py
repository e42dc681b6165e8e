"""MJX's contacts against MuJoCo C's, pair by pair: MJX's own functions and the ports.

For every geom pair MuJoCo C collides (height fields and SDFs aside), draws
random sizes, relative poses and margins around contact
(`mjstamp.colliders.compare.draw`: penetrating, touching, separated by
less than the margin, a few misses, a fifth axis-aligned) and collides each
draw in MuJoCo C and in MJX, once with MJX's own collision function and once
with the installed table (mjstamp's ports of C's routines where there are
any; `contacts.exact_meshes()` is on here, so the mesh pairs MJX collides
itself by default are measured with their ports too). Prints, per pair and
engine, the draws whose number of active contacts differs from C's and the
worst difference of distance, position, normal and frame over the rest, and
the time per pair-collision (jitted, vmapped over the draws, median of 3);
with --grad also that of a value and gradient with respect to the geom poses.

Usage: python benchmarks/perf/contacts.py [--pairs box-box,plane-box] [--draws 10000]
       [--seed 1] [--grad] [--json] [--save FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run by its path: the repository root holds `benchmarks`
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import save_json  # noqa: E402

PAIRS = (
    "plane-sphere", "plane-capsule", "plane-ellipsoid", "plane-cylinder", "plane-box",
    "plane-mesh", "sphere-sphere", "sphere-capsule", "sphere-ellipsoid", "sphere-cylinder",
    "sphere-box", "sphere-mesh", "capsule-capsule", "capsule-ellipsoid", "capsule-cylinder",
    "capsule-box", "capsule-mesh", "ellipsoid-ellipsoid", "ellipsoid-cylinder",
    "ellipsoid-box", "ellipsoid-mesh", "cylinder-cylinder", "cylinder-box", "cylinder-mesh",
    "box-box", "box-mesh", "mesh-mesh",
)


def _timed(pm, draws, grad: bool = False) -> float:
    """µs per pair-collision of the installed table (jitted, vmapped; median of 3).

    With `grad`: of the value and gradient of the active contacts' distances
    and positions (summed) with respect to the geom poses.
    """
    import jax
    import jax.numpy as jnp

    from mjstamp import colliders
    from mjstamp.colliders import compare

    fn = compare.mjx_collide(pm.xml, colliders.table_version())
    args = [jnp.asarray(a) for a in (draws.size, draws.rbound, draws.margin, draws.gap,
                                     draws.qpos, *compare.c_poses(pm, draws))]
    if grad:
        collide = fn

        def total(xpos, xmat, *rest):
            rows, active = collide(*rest, xpos, xmat)
            return jnp.sum(jnp.where(active, rows[..., 0] + rows[..., 1:4].sum(-1), 0.0))

        vg = jax.jit(jax.value_and_grad(total, argnums=(0, 1)))
        args = [args[5], args[6], *args[:5]]
        fn = vg
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return sorted(times)[1] / len(draws) * 1e6


def measure(name: str, draws: int, seed: int, grad: bool = False) -> dict:
    """One pair's row: C's contact count, then per engine the comparison and the cost."""
    import numpy as np

    from mjstamp import colliders
    from mjstamp.colliders import compare

    pm = compare.pair_model(*compare.parse_pair(name))
    dr = compare.draw(pm, draws, np.random.default_rng(seed))
    c = compare.c_contacts(pm, dr)
    row = {"pair": name, "draws": draws, "contacts_c": int(sum(len(a) for a in c)),
           "ported": pm.name in _ported_names()}
    for engine in ("installed", "mjx"):
        try:
            if engine == "mjx":
                with colliders.mjx_own():
                    j = compare.mjx_contacts(pm, dr)
                    us = _timed(pm, dr)
                    us_grad = _timed(pm, dr, grad=True) if grad else None
            else:
                j = compare.mjx_contacts(pm, dr)
                us = _timed(pm, dr)
                us_grad = _timed(pm, dr, grad=True) if grad else None
        except NotImplementedError:
            row[engine] = {"collided": False}
            continue
        report = compare.compare(pm, dr, c, j).as_dict()
        report.pop("pair")
        report.pop("draws")
        report.pop("contacts_c")
        row[engine] = {"collided": True, **report, "us_per_pair": us}
        if grad:
            row[engine]["us_per_pair_value_and_grad"] = us_grad
    return row


def _ported_names() -> set[str]:
    from mjstamp import colliders
    from mjstamp.colliders import compare

    colliders.patch_collisions()
    return {compare.pair_name(*p) for p in colliders.PORTED}


def _line(row: dict) -> str:
    out = [f"{row['pair']:<20} C contacts {row['contacts_c']:>6}"]
    for engine in ("mjx", "installed"):
        r = row[engine]
        if not r["collided"]:
            out.append(f"{engine}: not collided")
            continue
        out.append(f"{engine}: count mismatches {r['count_mismatches']:>5}, dist "
                   f"{r['dist']:.1e} pos {r['pos']:.1e} frame {r['frame']:.1e}, "
                   f"{r['us_per_pair']:.2f} us")
    return " | ".join(out)


def _save(path: Path, rows: list[dict], args) -> None:
    """Writes the rows measured so far into `path`, replacing its rows of the same pairs.

    N.B. after every pair, so that a long run keeps what it measured; rows of
    other pairs already in the file (another run, the same draws and seed) stay.
    """
    old = json.loads(path.read_text()) if path.exists() else {}
    keep = []
    if (old.get("draws"), old.get("seed")) == (args.draws, args.seed):
        done = {r["pair"] for r in rows}
        keep = [r for r in old.get("pairs", []) if r["pair"] not in done]
    order = {name: i for i, name in enumerate(PAIRS)}
    merged = sorted(keep + rows, key=lambda r: order.get(r["pair"], len(order)))
    out = {"draws": args.draws, "seed": args.seed, "precision": "float64", "pairs": merged}
    save_json(path, out, indent=1)


def main(argv: list[str] | None = None) -> int:
    """Runs the comparison of the pairs asked for and prints a line (or JSON) per pair."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=",".join(PAIRS), help="comma-separated TYPE-TYPE")
    parser.add_argument("--draws", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--grad", action="store_true",
                        help="also time value and gradient (a GJK/EPA gradient compiles for "
                        "minutes)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--save", metavar="FILE",
                        help="also write the JSON there, after each pair (merged with the "
                        "file's rows of other pairs, same draws and seed)")
    args = parser.parse_args(argv)
    import mjstamp

    mjstamp.configure(precision="float64")
    from mjstamp import colliders
    from mjstamp.colliders import compare

    colliders.exact_meshes()

    names = [p.strip() for p in args.pairs.split(",") if p.strip()]
    for name in names:
        compare.parse_pair(name)  # one line for a bad name, before any work
    rows = []
    for name in names:
        t0 = time.perf_counter()
        rows.append(measure(name, args.draws, args.seed, grad=args.grad))
        rows[-1]["seconds"] = time.perf_counter() - t0
        if not args.json:
            print(_line(rows[-1]), flush=True)
        if args.save:
            _save(Path(args.save), rows, args)
    out = {"draws": args.draws, "seed": args.seed, "precision": "float64", "pairs": rows}
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
