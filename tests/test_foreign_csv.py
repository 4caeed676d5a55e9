"""SimpleForest and aRchi CSV writers: round trips through the bundled readers, and the derived
columns agree with what SimpleForest itself wrote."""

import numpy as np
import pytest

import bforest_core as bf
from bforest_formats.foreign_csv import segments, stem_branch_id
from conftest import hand_tree, qsm_path, read_sample


@pytest.mark.parametrize("fmt", ["simpleforest-csv", "archi-csv"])
@pytest.mark.parametrize("sample", ["pine_ruotsinkyla_3.mat", "coffeetree_archi.csv", "coffeetree_simpleforest.csv"])
def test_round_trip(tmp_path, fmt, sample):
    t = read_sample(sample)
    back = bf.read_qsm(bf.write_tree(t, tmp_path / "tree.csv", format=fmt))
    assert back.metadata["format"] == fmt and back.n == t.n
    assert np.abs(back.start - t.start).max() < 1e-6 and np.abs(back.radius - t.radius).max() < 1e-6
    assert np.array_equal(back.parent, t.parent) and np.array_equal(back.order, t.order)
    assert np.array_equal(back.branch, t.branch)


def test_segments_and_branch_ids_of_the_hand_tree():
    t = hand_tree()
    seg, seg_parent, last, reverse = segments(t)
    # forks at trunk 0 (-> trunk 1, lateral A) and trunk 1 (-> trunk 2, B); trunk 2 has one child (C),
    # so C continues trunk 2's segment
    assert seg.tolist() == [0, 1, 2, 3, 3, 4, 2]
    assert seg_parent.tolist() == [-1, 0, 1, 0, 1] and last.tolist() == [0, 1, 6, 4, 5]
    assert reverse.tolist() == [3, 2, 1, 1, 1]
    ids = stem_branch_id(t)
    assert ids[:3].tolist() == [0, 0, 0] and ids[3] == ids[4] and sorted({ids[3], ids[5], ids[6]}) == [1, 2, 3]


def test_derived_columns_agree_with_simpleforest():
    """segmentID, branchID and reverseBranchOrder as SimpleForest wrote them for the coffee tree."""
    raw = np.genfromtxt(qsm_path("coffeetree_simpleforest.csv"), delimiter=",", skip_header=1)
    t = bf.read_qsm(qsm_path("coffeetree_simpleforest.csv"))
    seg, _, _, reverse = segments(t)
    f = raw[t.source_row]

    def same_partition(a, b):
        return len(set(zip(a, b))) == len(set(a)) == len(set(b))

    assert same_partition(seg, f[:, 12].astype(int)) and len(set(seg)) == 133
    assert same_partition(stem_branch_id(t), f[:, 16].astype(int))
    assert np.array_equal(reverse[seg], f[:, 15].astype(int))
