"""The sample plan of a data set: which sample is what, decided before anything is solved.

Every per-sample choice is a pure function of the configuration and the sample index, so
that any sample can be recomputed alone and in any order (the basis of exact resumption):

* Samples ``0 .. n_samples-1`` are LBO samples; samples ``n_samples .. n_samples+n_test2-1``
  are test-2 samples (LSC fields blended with a fresh LBO field).
* Split of the LBO samples: a permutation drawn from
  ``numpy.random.default_rng(SeedSequence([seed, SPLIT_STREAM]))``; the first
  ``round(n * r_train / sum(r))`` permuted indices are ``train``, the next
  ``round(n * r_valid / sum(r))`` are ``valid``, the rest ``test1``.
* Test-2 sample ``j`` (0-based within the test-2 block) gets ``beta = betas[j % len(betas)]``,
  so the counts per beta differ by at most one (200 samples over 11 betas: 19 or 18 each).
* Per-sample seed: ``SeedSequence([seed, index]).generate_state(1, uint64)[0]``; the sample's
  random numbers come from ``numpy.random.default_rng(sample_seed)`` and nothing else.
* Generation order (:func:`generation_order`): the splits are interleaved in proportion, so
  a store stopped part-way (or a long run inspected while it goes) holds train, valid,
  test-1 and test-2 samples in the planned ratio. The order changes no sample's numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config

__all__ = ["SPLIT_NAMES", "SPLIT_CODES", "SamplePlan", "make_plan", "sample_seed", "generation_order", "SPLIT_STREAM"]

#: Integer codes of the split labels, as stored in ``samples/split``.
SPLIT_NAMES: dict[int, str] = {0: "train", 1: "valid", 2: "test1", 3: "test2"}
SPLIT_CODES: dict[str, int] = {v: k for k, v in SPLIT_NAMES.items()}

#: Second SeedSequence entropy word of the split permutation (no sample index reaches it).
SPLIT_STREAM = 2**63 - 1


def sample_seed(base_seed: int, index: int) -> np.uint64:
    """The 64-bit seed of sample ``index``: ``SeedSequence([base_seed, index])``'s first word."""
    return np.random.SeedSequence([int(base_seed), int(index)]).generate_state(1, np.uint64)[0]


@dataclass(frozen=True, eq=False)
class SamplePlan:
    """What every sample of a data set is.

    Attributes:
        split: (N,) int8 split codes (see :data:`SPLIT_NAMES`).
        beta: (N,) float64 LBO share of test-2 samples; NaN for LBO samples.
        seed: (N,) uint64 per-sample seeds.
        n_lbo: number of LBO samples (they come first).
    """

    split: np.ndarray
    beta: np.ndarray
    seed: np.ndarray
    n_lbo: int

    @property
    def n_samples(self) -> int:
        """Total number of samples N (LBO + test-2)."""
        return len(self.split)

    def is_test2(self, index: int) -> bool:
        """Whether sample ``index`` is a test-2 (LSC/beta) sample."""
        return index >= self.n_lbo

    def counts(self) -> dict[str, int]:
        """Number of samples per split label."""
        return {name: int(np.sum(self.split == code)) for code, name in SPLIT_NAMES.items()}


def split_sizes(n: int, split) -> tuple[int, int, int]:
    """``(train, valid, test-1)`` sample counts of ``n`` LBO samples at the ratio ``split``
    (``dataset.split``, three non-negative numbers), as :func:`make_plan` assigns them."""
    ratios = np.asarray(split, dtype=np.float64)
    n_train = int(round(n * ratios[0] / ratios.sum()))
    n_valid = min(n - n_train, int(round(n * ratios[1] / ratios.sum())))
    return n_train, n_valid, n - n_train - n_valid


def make_plan(cfg: Config) -> SamplePlan:
    """The plan of the data set described by ``cfg.dataset`` and ``cfg.forces.betas``."""
    ds = cfg.dataset
    n, n2 = ds.n_samples, ds.n_test2
    n_train, n_valid, _ = split_sizes(n, ds.split)
    perm = np.random.default_rng(np.random.SeedSequence([ds.seed, SPLIT_STREAM])).permutation(n)
    split = np.empty(n + n2, dtype=np.int8)
    split[perm[:n_train]] = SPLIT_CODES["train"]
    split[perm[n_train : n_train + n_valid]] = SPLIT_CODES["valid"]
    split[perm[n_train + n_valid :]] = SPLIT_CODES["test1"]
    split[n:] = SPLIT_CODES["test2"]
    beta = np.full(n + n2, np.nan)
    betas = np.asarray(cfg.forces.betas, dtype=np.float64)
    beta[n:] = betas[np.arange(n2) % len(betas)]
    seed = np.array([sample_seed(ds.seed, i) for i in range(n + n2)], dtype=np.uint64)
    return SamplePlan(split=split, beta=beta, seed=seed, n_lbo=n)


def generation_order(split: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """The order in which to solve the samples ``indices``: splits interleaved in proportion.

    Sample ``i``, the ``k``-th (0-based, by index) of the ``n_s`` samples of its split in
    ``indices``, gets the key ``(k + 1/2) / n_s``; samples are taken by ascending key (ties
    by index). Every prefix of the order then holds each split within one sample of its
    share, and within a split the samples come by index (test-2 betas cycle).

    Args:
        split: (N,) split codes of the whole data set.
        indices: (m,) indices of the samples to order (e.g. the pending ones).

    Returns:
        (m,) int64, a permutation of ``indices``.
    """
    idx = np.sort(np.asarray(indices, dtype=np.int64))
    codes = np.asarray(split)[idx]
    key = np.empty(len(idx))
    for c in np.unique(codes):
        members = np.flatnonzero(codes == c)
        key[members] = (np.arange(len(members)) + 0.5) / len(members)
    return idx[np.lexsort((idx, key))]
