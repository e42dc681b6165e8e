"""Which particles a solve returns: plans kept from the run, the screen and robust selection.

No plan found is lost: a particle that left a verified plan takes it back
(`keep_visited`), the screen's task plans no particle holds take spare
particles (`keep_screened`), and each task plan keeps its most robust
candidates (`select_robust`). Each keeps the particle count, and gives a
particle back where MJX does not predict its new plan to succeed
(`take_or_give_back`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np

from mjstamp import verify
from mjstamp.scenes import uncertainty
from mjstamp.solver.outcome import (
    Outcome,
)


def keep_visited(theta, final: Outcome, visited):
    """Per particle, the best plan it visited: its final state or an earlier snapshot.

    A particle can pass through a plan that succeeds and leave it (SVGD's
    repulsion or an Adam step out of a narrow valley). No plan found is lost:
    a particle whose final state is not a returned, verified plan takes its
    latest snapshot that is one; then a particle whose final task plan other
    particles also hold takes a snapshot whose task plan none holds, if it has
    one. Deterministic (particles in index order, later snapshots first).

    Args:
      theta: (n, d) final particles.
      final: their `Outcome`.
      visited: {name: ((n, d) earlier particles, their `Outcome`)}, latest first.

    Returns:
      (theta (n, d) with chosen snapshots, source (n,) names: "final" or a key
      of `snapshots`).
    """
    ok = final.good.copy()
    plan = np.asarray(final.verified.plan, dtype=object).copy()
    theta = theta.copy()
    source = np.full(len(theta), "final", dtype=object)
    counts = Counter(plan[ok])
    seen = {name: (snap, o.good, np.asarray(o.verified.plan, dtype=object))
            for name, (snap, o) in visited.items()}
    for i in np.flatnonzero(~ok):
        for name, (snap, good, plan_s) in seen.items():
            if good[i]:
                theta[i], source[i], plan[i], ok[i] = snap[i], name, plan_s[i], True
                counts[plan_s[i]] += 1
                break
    for i in np.flatnonzero(ok & (source == "final")):
        if counts[plan[i]] < 2:
            continue
        for name, (snap, good, plan_s) in seen.items():
            if good[i] and counts[plan_s[i]] == 0:
                counts[plan[i]] -= 1
                theta[i], source[i], plan[i] = snap[i], name, plan_s[i]
                counts[plan_s[i]] += 1
                break
    return theta, source


def keep_screened(theta, source, outcome: Outcome, successes: dict[str, np.ndarray],
                   evaluate: Callable[..., Outcome]):
    """Returns the screen's task plans that no particle holds, in place of spare particles.

    The screen's successes succeeded in MuJoCo C with the scene's own solver:
    they are verified plans the solve found, and no plan found is lost. For
    each task plan the screen reached and no returned, verified particle holds
    (best screen cost first), a spare particle takes the screen's best
    candidate of it: first particles that are not returned and verified, then
    those whose task plan others hold too (later ones first). A candidate MJX
    does not predict to succeed gives its particle back. The particle count
    stays n (nothing is compiled again).

    Returns:
      (theta, source with "screen" where a candidate was taken, their `Outcome`).
    """
    good = outcome.good
    plan = np.asarray(outcome.verified.plan, dtype=object)
    held = set(plan[good])
    missing = [pool[0] for p, pool in successes.items() if p not in held and len(pool)]
    counts = Counter(plan[good])
    spare = list(np.flatnonzero(~good))
    for i in np.flatnonzero(good)[::-1]:
        if counts[plan[i]] > 1:
            counts[plan[i]] -= 1
            spare.append(i)
    idx = np.asarray(spare[: len(missing)], dtype=int)
    if not idx.size:
        return theta, source, outcome
    new, new_source = theta.copy(), source.copy()
    new[idx], new_source[idx] = np.stack(missing[: idx.size]), "screen"
    return take_or_give_back(theta, source, new, new_source, idx, evaluate)


def take_or_give_back(theta, source, new, new_source, changed, evaluate, plan=None):
    """Evaluates `new`; rows of `changed` MJX does not predict to succeed get `theta`'s back.

    With `plan`, a row MJX predicts to succeed in another task plan than
    `plan`'s gets its particle back too.

    Returns:
      (theta, source, their `Outcome`) as kept.
    """
    new_outcome = evaluate(new)
    bad = ~new_outcome.good[changed]
    if plan is not None:
        bad |= new_outcome.verified.plan[changed] != plan[changed]
    back = changed[bad]
    if back.size:
        new[back], new_source[back] = theta[back], source[back]
        new_outcome = evaluate(new)
    return new, new_source, new_outcome


SELECT_SAMPLES = 32
"""Fewest perturbed C replays robust selection scores a candidate on (`robust.select`)."""


def select_robust(problem, cfg, theta, source, outcome: Outcome, successes, evaluate, seed,
                   say):
    """Each verified task plan's particles take its most robust candidates (`robust.select`).

    Candidates of a task plan: the returned, verified particles holding it and
    the first `robust.select` of the screen's successes in it (best C cost
    first), all scored by `verify.robustness` on `SELECT_STREAM` draws. The
    plan's particles keep those of themselves among its best scored and the
    rest take the best screen candidates (source "screen"); one MJX does not
    predict to succeed gives its particle back. Task plans and the particle
    count are unchanged.
    """
    good = outcome.good
    plan = np.asarray(outcome.verified.plan, dtype=object)
    groups = []
    for p in sorted(set(plan[good])):
        mine = np.flatnonzero(good & (plan == p))
        pool = np.asarray(successes.get(p, ()), np.float64).reshape(-1, theta.shape[1])
        groups.append((p, mine, pool[: cfg.robust.select]))
    if not sum(len(pool) for _, _, pool in groups):
        return theta, source, outcome
    samples = max(cfg.verify.robustness_samples, SELECT_SAMPLES)
    candidates = np.concatenate([np.concatenate([theta[mine], pool]) for _, mine, pool in groups])
    say(f"robust selection: scoring {len(candidates)} candidates of {len(groups)} task plans "
        f"({samples} perturbed MuJoCo C replays each)")
    scores = verify.robustness(problem, candidates, samples=samples, seed=seed,
                               stream=uncertainty.SELECT_STREAM).success
    new, new_source, start = theta.copy(), source.copy(), 0
    for _, mine, pool in groups:
        score = scores[start : start + len(mine) + len(pool)]
        start += len(mine) + len(pool)
        best = np.argsort(-score, kind="stable")[: len(mine)]  # N.B. ties: particles first
        taken = [j - len(mine) for j in best if j >= len(mine)]  # pool rows among the best
        losers = [i for k, i in enumerate(mine) if k not in set(best)]
        for i, j in zip(losers, taken, strict=True):
            new[i], new_source[i] = pool[j], "screen"
    changed = np.flatnonzero(new_source != source)
    if not changed.size:
        return theta, source, outcome
    return take_or_give_back(theta, source, new, new_source, changed, evaluate, plan)


