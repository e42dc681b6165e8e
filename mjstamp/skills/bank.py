"""A skill bank: fitted DMPs by name, kept in one versioned file, refitted when stale.

The file is a single ``.npz`` (numpy arrays only, read with allow_pickle=False):

    format       "mjstamp-skill-bank"
    version      FORMAT_VERSION
    header       JSON: {"fingerprint": str, "meta": {...},
                        "skills": [{"name": str, "config": {DMPConfig fields}}, ...]}
    weights_<i>  (n_basis, dim) float64 weights of skills[i]

The fingerprint is the caller's: a hash of whatever made the demonstrations
(their code, the scene). A bank whose fingerprint differs from the one asked
for is *stale*: its skills imitate demonstrations that the code no longer makes.

What `load_or_fit` does with each kind of file:

- missing, stale, or written by an *older* format version: fit, overwrite, and
  say so in one line (the file is ours, made from code, and refitting rebuilds
  it exactly);
- unreadable (not an npz, wrong format tag, a broken header) or written by a
  *newer* format version: error. A file we cannot read may not be a bank we
  wrote (a mistyped path) or may belong to a newer mjstamp; overwriting it
  could destroy someone's data, so the user deletes it.

References:
  STAMP §IV-C ("a bank of goal-conditioned DMPs ... whose weights we train offline").
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mjstamp.errors import MjstampError, valid_list
from mjstamp.fileio import probe, write_atomic
from mjstamp.skills.dmp import DMP, DMPConfig

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MissingSkillBank",
    "SkillBank",
    "StaleSkillBank",
    "load",
    "load_or_fit",
    "save",
]

FORMAT = "mjstamp-skill-bank"
FORMAT_VERSION = 1  # 1: npz with a JSON header and one weights_<i> array per skill


class MissingSkillBank(MjstampError):
    """No skill-bank file at the path: `load_or_fit` fits one."""


class StaleSkillBank(MjstampError):
    """A readable skill bank made for other demonstrations (fingerprint) or by an older format."""


@dataclasses.dataclass(frozen=True)
class SkillBank:
    """Fitted skills by name, with the fingerprint of what made their demonstrations.

    Attributes:
      skills: skill name -> fitted DMP.
      fingerprint: the caller's identifier of the demonstration-generating code
        and scene (e.g. a hash); a bank is stale when it differs.
      meta: free-form JSON-able notes (how the demonstrations were made, ...).
    """

    skills: Mapping[str, DMP]
    fingerprint: str
    meta: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def skill(self, name: str) -> DMP:
        """The DMP called `name`; a one-line MjstampError lists the valid names."""
        if name not in self.skills:
            raise MjstampError(f"no skill {name!r} in the bank; valid: {valid_list(self.skills)}")
        return self.skills[name]


def save(bank: SkillBank, path: str | os.PathLike) -> Path:
    """Writes a skill bank atomically (temporary sibling + os.replace).

    Args:
      bank: the SkillBank to write.
      path: target file (conventionally ``*.npz``); parent folders are created.

    Returns:
      The path written.

    Raises:
      MjstampError: a skill name that is not a non-empty string, a skill that is
        not a DMP, non-finite weights, a non-string fingerprint or meta that
        JSON cannot encode.
    """
    path = Path(path)
    if not isinstance(bank.fingerprint, str):
        raise MjstampError(
            f"skill bank fingerprint {bank.fingerprint!r}: need a string (e.g. a hash)"
        )
    arrays: dict[str, np.ndarray] = {}
    entries = []
    for i, (name, dmp) in enumerate(bank.skills.items()):
        if not isinstance(name, str) or not name:
            raise MjstampError(f"skill bank skill name {name!r}: need a non-empty string")
        if not isinstance(dmp, DMP):
            raise MjstampError(f"skill bank skill {name!r} is a {type(dmp).__name__}: need a DMP")
        weights = np.asarray(dmp.weights, dtype=np.float64)
        if weights.ndim != 2 or not np.all(np.isfinite(weights)):
            raise MjstampError(
                f"skill bank skill {name!r} has weights of shape {weights.shape} "
                "with non-finite values or not (n_basis, dim): refit it"
            )
        arrays[f"weights_{i}"] = weights
        entries.append({"name": name, "config": dataclasses.asdict(dmp.config)})
    try:
        header = json.dumps(
            {"fingerprint": bank.fingerprint, "meta": dict(bank.meta), "skills": entries}
        )
    except (TypeError, ValueError) as e:
        raise MjstampError(f"skill bank meta cannot be saved as JSON: {e}") from None
    arrays.update(
        format=np.array(FORMAT), version=np.array(FORMAT_VERSION), header=np.array(header)
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, lambda f: np.savez_compressed(f, **arrays))
    return path


def load(path: str | os.PathLike, *, fingerprint: str | None = None) -> SkillBank:
    """Reads a skill bank written by `save`, checking its format, version and fingerprint.

    Args:
      path: the bank file.
      fingerprint: the fingerprint the caller's demonstrations have now; None
        skips the staleness check.

    Returns:
      The SkillBank (weights as float64 numpy arrays).

    Raises:
      MissingSkillBank: no file at `path`.
      StaleSkillBank: the fingerprint differs, or an older format version.
      MjstampError: an unreadable file, another format, or a newer version.
    """
    path = Path(path)
    if not probe(path.is_file, path, "skill bank "):
        raise MissingSkillBank(f"skill bank {str(path)!r}: no such file")
    unreadable = f"skill bank {str(path)!r} is unreadable"
    fix = "delete or move it to refit"
    try:
        with np.load(path, allow_pickle=False) as npz:
            files = dict(npz.items())
    except Exception as e:  # noqa: BLE001 - any failure to parse means "not a bank we can read"
        raise MjstampError(f"{unreadable} ({type(e).__name__}: not an .npz); {fix}") from None
    tag = files.get("format")
    if tag is None or tag.shape != () or str(tag) != FORMAT:
        raise MjstampError(f"{unreadable}: it is not a {FORMAT!r} file; {fix}")
    try:
        version = int(files["version"])
    except (KeyError, TypeError, ValueError):
        raise MjstampError(f"{unreadable}: no format version; {fix}") from None
    if version > FORMAT_VERSION:
        raise MjstampError(
            f"skill bank {str(path)!r} was written by format version {version}; this mjstamp "
            f"reads version {FORMAT_VERSION}: upgrade mjstamp, or delete it to refit"
        )
    if version < FORMAT_VERSION:
        raise StaleSkillBank(
            f"skill bank {str(path)!r} was written by format version {version}; this mjstamp "
            f"reads version {FORMAT_VERSION}: delete it to refit"
        )
    try:
        header = json.loads(str(files["header"]))
        skills = {}
        for i, entry in enumerate(header["skills"]):
            config = DMPConfig(**entry["config"])
            weights = files[f"weights_{i}"].astype(np.float64)
            if weights.ndim != 2 or weights.shape[0] != config.n_basis:
                raise ValueError(f"weights_{i} has shape {weights.shape}")
            skills[str(entry["name"])] = DMP(weights=weights, config=config)
        bank = SkillBank(
            skills=skills, fingerprint=str(header["fingerprint"]), meta=dict(header["meta"])
        )
    except (KeyError, TypeError, ValueError) as e:
        raise MjstampError(
            f"{unreadable}: broken header ({type(e).__name__}: {e}); {fix}"
        ) from None
    if fingerprint is not None and bank.fingerprint != fingerprint:
        raise StaleSkillBank(
            f"skill bank {str(path)!r} is stale: fitted for fingerprint {bank.fingerprint!r}, "
            f"the demonstrations now give {fingerprint!r}; refit it or delete it"
        )
    return bank


def load_or_fit(
    path: str | os.PathLike,
    fingerprint: str,
    fit_fn: Callable[[], SkillBank],
    *,
    say: Callable[[str], None] | None = None,
) -> SkillBank:
    """Loads the bank at `path`, or fits and saves a new one if missing or stale.

    Args:
      path: the bank file.
      fingerprint: the fingerprint of the demonstrations as the code makes them now.
      fit_fn: makes the bank from scratch; it must carry `fingerprint`.
      say: receives one line before a (re)fit; None prints it to stderr.

    Returns:
      The loaded or freshly fitted SkillBank.

    Raises:
      MjstampError: the file is unreadable or from a newer format (never
        overwritten: see the module docstring), or `fit_fn` returned a bank
        with another fingerprint.
    """
    try:
        return load(path, fingerprint=fingerprint)
    except MissingSkillBank:
        notice = f"skill bank {str(path)!r} not found: fitting the skills"
    except StaleSkillBank as e:
        notice = f"{e} -> refitting and overwriting"
    (say or _stderr)(notice)
    bank = fit_fn()
    if not isinstance(bank, SkillBank) or bank.fingerprint != fingerprint:
        got = bank.fingerprint if isinstance(bank, SkillBank) else type(bank).__name__
        raise MjstampError(
            f"load_or_fit: fit_fn returned a bank with fingerprint {got!r}; "
            f"need a SkillBank with fingerprint {fingerprint!r}"
        )
    save(bank, path)
    return bank


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


