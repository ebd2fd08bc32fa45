"""nodegraph.flags: the one reading of a flags ParamSequence (named column, > 0.5, NaN set)."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import InputError, ParamSequence
from nodegraph.flags import flags_to_mask, mask_to_flags


def test_flags_to_mask_reads_the_failed_column_and_counts_nan_as_set():
    values = np.array([[0.0, 9.0], [1.0, 0.0], [np.nan, 0.0], [0.4, 1.0], [0.6, 0.0], [np.inf, 0.0]], np.float32)
    assert flags_to_mask(ParamSequence(values, ["failed", "energy_ratio"]), 6).tolist() == \
        [False, True, True, False, True, True]
    by_name = ParamSequence(values[:, ::-1].copy(), ["energy_ratio", "failed"])
    assert flags_to_mask(by_name, 6).tolist() == [False, True, True, False, True, True]
    first = ParamSequence(values[:, :1].copy(), ["flag"])  # no 'failed' column: the first one
    assert flags_to_mask(first, 6).tolist() == [False, True, True, False, True, True]
    assert flags_to_mask(ParamSequence(values, ["failed", "energy_ratio"]), 6, name="energy_ratio").tolist() == \
        [True, False, False, True, False, False]


def test_flags_to_mask_without_flags_and_errors():
    assert flags_to_mask(None, 4).tolist() == [False] * 4
    with pytest.raises(InputError, match=r"expected flags for 5 frames, found 3") as info:
        flags_to_mask(ParamSequence(np.zeros((3, 1), np.float32), ["failed"]), 5, where="still_failed")
    assert info.value.port == "still_failed"
    with pytest.raises(InputError, match=r"expected \(F, 1\) flags with a 'failed' column, found shape \(3, 0\)"):
        flags_to_mask(ParamSequence(np.zeros((3, 0), np.float32), []), 3)


def test_mask_to_flags_round_trip():
    mask = np.array([True, False, False, True])
    flags = mask_to_flags(mask)
    assert flags.names == ["failed"] and flags.values.dtype == np.float32 and flags.values.shape == (4, 1)
    assert flags.values[:, 0].tolist() == [1.0, 0.0, 0.0, 1.0]
    assert flags_to_mask(flags, 4).tolist() == mask.tolist()
    flags.validate()
