"""The separation profile's group factors and leave-one-group-out residuals combined in stacked QR calls
(afmid.fit.regression.combine_each, afmid.fit.profile.GroupedProfile.leave_each_out): the same LAPACK routine on the
same matrices as one regression.combine per group, so the same bits are required (np.array_split's groups of two
sizes, columns spanning many orders of magnitude as SI columns do)."""

from __future__ import annotations

import numpy as np

import afmid.fit.regression as regression
from afmid.fit.profile import GroupedProfile


def _factors(n_blocks=77, q=6, seed=2):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n_blocks, 3 * q, q)) * np.logspace(-18, 4, q)
    return np.linalg.qr(A, mode="r")


def test_stacked_combines_are_the_one_by_one_combines():
    T = _factors()
    stacks = np.stack([T[:7], T[7:14], T[14:21]])
    assert np.array_equal(regression.combine_each(stacks), np.stack([regression.combine(s) for s in stacks]))


def test_leave_each_out_is_leave_out_of_every_group():
    T = _factors()
    profile = GroupedProfile(lambda value: (T * (1.0 + value), 1000), None)
    profile(0.25)
    parts = np.array_split(np.arange(T.shape[0]), profile.jackknife_groups())
    assert len({p.size for p in parts}) == 2  # 77 blocks in 12 groups: 7 and 6
    expected_groups = np.stack([regression.combine(T[p] * 1.25) for p in parts])
    assert np.array_equal(profile.groups[0.25], expected_groups)
    one_by_one = [profile.leave_out(0.25, g) for g in range(profile.jackknife_groups())]
    assert np.array_equal(profile.leave_each_out(0.25), np.array(one_by_one))
    assert np.all(np.isinf(profile.leave_each_out(0.5)))  # not evaluated: no groups there
