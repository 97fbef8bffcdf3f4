"""Seed derivation, written once: every random choice in knotlab is seeded through these.

All derivations go through NumPy's `SeedSequence`, whose output is defined by NumPy's spec and
does not depend on the machine, so a derived seed is the same everywhere:
- ``derive_seed(a, b, ...)``: a 32-bit seed from an ordered tuple of integers (episode step
  seeds, per-task observation seeds, retry seeds);
- ``child_seed(seed, *key)``: the seed of item ``key`` spawned from ``seed`` (library candidates,
  task indices per split); spawn keys keep children of one seed disjoint from each other;
- ``generator(a, b, ...)``: a Generator seeded from an ordered tuple (the expert's jitters).
"""

from __future__ import annotations

import numpy as np


def derive_seed(*parts: int) -> int:
    """32-bit seed of the integer tuple ``parts`` (SeedSequence(parts).generate_state(1)[0])."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0])


def child_seed(seed: int, *spawn_key: int) -> int:
    """32-bit seed of child ``spawn_key`` of ``seed`` (SeedSequence(seed, spawn_key=key))."""
    ss = np.random.SeedSequence(entropy=int(seed), spawn_key=tuple(int(k) for k in spawn_key))
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def generator(*parts: int) -> np.random.Generator:
    """A Generator seeded by the integer tuple ``parts``."""
    return np.random.default_rng(np.random.SeedSequence([int(p) for p in parts]))


def text_seed(seed: int, text: str) -> int:
    """32-bit seed of ``seed`` and a string key (a task id): order-free per-item randomness."""
    import hashlib

    digest = int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")
    return derive_seed(int(seed), digest)


def text_uniform(seed: int, text: str) -> float:
    """A uniform number in [0, 1) fixed by ``seed`` and a string key."""
    return text_seed(seed, text) / 2.0**32
