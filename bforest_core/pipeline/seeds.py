"""Model seeds of a run: of its evaluations, clones, noise measurements and held-out scores.

With ``seed_mode = "fixed"`` (the paper: the SSM seed is held fixed while optimising) every
evaluation uses the same K model seeds; with ``"per_evaluation"`` they come from the run seed and
the evaluation index. Every stream derives from :class:`numpy.random.SeedSequence` of the run seed
and a tag of its own, never from worker state, so results do not depend on the executor or the
number of workers, and no two streams share a seed.
"""

from __future__ import annotations

import numpy as np


def _seed_stream(key: list[int], k: int) -> list[int]:
    """``k`` independent 32-bit seeds of the stream ``key`` (a run seed and the stream's tag)."""
    return [int(s.generate_state(1, np.uint32)[0]) for s in np.random.SeedSequence(key).spawn(k)]


def model_seeds(run_seed: int, k: int, mode: str = "fixed", index: int = 0) -> list[int]:
    """The K model seeds of one evaluation."""
    return _seed_stream([int(run_seed), 1] if mode == "fixed" else [int(run_seed), 2, int(index)], k)


def spread_seeds(run_seed: int, k: int) -> list[int]:
    """Model seeds for measuring the objective's seed noise (distinct from fitting and clone seeds)."""
    return _seed_stream([int(run_seed), 4], k)


def heldout_seeds(run_seed: int, sets: int, per: int) -> list[list[int]]:
    """``sets`` sets of ``per`` model seeds that no fit, noise measurement or clone of this run
    seed uses: for scoring best points on trees the fits never saw (``bforest compare --heldout``)."""
    flat = _seed_stream([int(run_seed), 5], sets * per)
    return [flat[i * per : (i + 1) * per] for i in range(sets)]


def repeat_seeds(base_seed: int, repeats: int) -> list[int]:
    """Run seeds of ``bforest compare``'s repeats: the base config's seed's own stream, so that
    comparisons from neighbouring base seeds share no run (``base + r`` made base 1's second
    repeat base 2's first)."""
    return _seed_stream([int(base_seed), 6], repeats)


def clone_seeds(run_seed: int, n: int, base: int | None = None) -> list[int]:
    """Fresh seeds for clones (distinct from the fitting seeds)."""
    return _seed_stream([int(run_seed if base is None else base), 3], n)


def realisation_clones(stand_seed: int, tree: int, n_clones: int, realisations: int) -> list[int]:
    """Which clone of tree number ``tree`` (of ``n_clones``) stands in each of a stand's
    ``realisations`` synthetic stands: a permutation from the stand seed's own stream, so no clone
    stands twice while the realisations are at most the clones."""
    rng = np.random.default_rng(np.random.SeedSequence([int(stand_seed), 6, int(tree)]))
    perm = rng.permutation(int(n_clones))
    return [int(perm[r % n_clones]) for r in range(int(realisations))]
