"""ClassTable, FruxelModel and the occupancy rule (conventions section 2)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fruxel.classes import DEFAULT_CLASSES, MAX_CLASSES, ClassTable, ClassTableError
from fruxel.grid import FruxelGrid
from fruxel.model import FruxelModel, ModelError, labels_from_scores

FAST = settings(max_examples=50, deadline=None)
GRID = FruxelGrid(width=6, height=5, depth=4, z_near=0.5, z_far=4.5, hfov=75.0)


def _random_labels(seed: int, grid: FruxelGrid = GRID, n: int = 7, p_empty: float = 0.6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lab = rng.integers(1, n, grid.shape)
    return np.where(rng.random(grid.shape) < p_empty, 0, lab).astype(np.uint8)


# ---------------------------------------------------------------------------------------------------- classes
def test_default_classes_follow_the_spec() -> None:
    assert DEFAULT_CLASSES.names == ("empty", "wall", "floor", "window", "furniture", "door", "sculpture")
    pal = DEFAULT_CLASSES.palette()
    assert pal.shape == (7, 3) and pal.dtype == np.uint8
    assert len({tuple(c) for c in pal.tolist()}) == 7, "default colours must be distinct"
    assert DEFAULT_CLASSES.index("door") == 5 and len(DEFAULT_CLASSES) == DEFAULT_CLASSES.n_classes == 7


def test_colour_of_is_vectorised() -> None:
    lab = _random_labels(0)
    col = DEFAULT_CLASSES.colour_of(lab)
    assert col.shape == lab.shape + (3,) and col.dtype == np.uint8
    for c in range(7):
        assert np.all(col[lab == c] == DEFAULT_CLASSES.colours[c])
    assert DEFAULT_CLASSES.colour_of(3).tolist() == list(DEFAULT_CLASSES.colours[3])
    with pytest.raises(ClassTableError):
        DEFAULT_CLASSES.colour_of(np.array([0, 7]))
    with pytest.raises(ClassTableError):
        DEFAULT_CLASSES.colour_of(np.array([0.0, 1.0]))


def test_indices_in_carries_labels_into_a_larger_table_by_name() -> None:
    small = ClassTable.from_names(["empty", "floor", "wall"])
    big = ClassTable.from_names(["empty", "wall", "window", "floor"])
    lut = small.indices_in(big)
    assert lut.tolist() == [0, 3, 1]
    labels = np.array([[0, 1], [2, 1]], dtype=np.uint8)
    assert [big.names[i] for i in lut[labels].ravel()] == [small.names[i] for i in labels.ravel()]
    with pytest.raises(ClassTableError, match="'window'"):
        big.indices_in(small)


def test_class_table_dict_round_trip_and_extension() -> None:
    table = DEFAULT_CLASSES.extended("plant", "lamp", colours=[(1, 2, 3)])
    assert table.names[-2:] == ("plant", "lamp") and table.colours[-2] == (1, 2, 3)
    assert len(set(table.colours)) == len(table), "automatic colours must not repeat existing ones"
    assert ClassTable.from_dict(table.to_dict()) == table
    assert table.to_dict()["names"][0] == "empty"
    own = ClassTable.from_names(["rock", "tree"])
    assert own.names == ("empty", "rock", "tree") and len(set(own.colours)) == 3
    big = ClassTable.from_names([f"c{i}" for i in range(MAX_CLASSES - 1)])
    assert len(big) == MAX_CLASSES and len(set(big.colours)) == MAX_CLASSES


@pytest.mark.parametrize(
    "names, colours",
    [
        ((), ()),
        (("wall",), ((0, 0, 0),)),
        (("empty", "wall", "wall"), ((0, 0, 0),) * 3),
        (("empty", ""), ((0, 0, 0),) * 2),
        (("empty", 3), ((0, 0, 0),) * 2),
        (("empty", "wall"), ((0, 0, 0),)),
        (("empty", "wall"), ((0, 0, 0), (256, 0, 0))),
        (("empty", "wall"), ((0, 0, 0), (1, 2))),
        (("empty", "wall"), ((0, 0, 0), (1.5, 2, 3))),
        ("empty", ((0, 0, 0),) * 5),
        (("empty",) + tuple(f"c{i}" for i in range(MAX_CLASSES)), ((0, 0, 0),) * (MAX_CLASSES + 1)),
    ],
)
def test_invalid_class_tables_are_refused(names, colours) -> None:
    with pytest.raises(ClassTableError):
        ClassTable(names, colours)


@pytest.mark.parametrize(
    "d",
    [[], {"names": ["empty"]}, {"names": ["empty"], "colours": [[0, 0, 0]], "x": 1}, {"names": "e", "colours": []}],
)
def test_invalid_class_dicts_are_refused(d) -> None:
    with pytest.raises(ClassTableError):
        ClassTable.from_dict(d)


# ---------------------------------------------------------------------------------------------------- occupancy rule
def _softmax(x: np.ndarray, axis: int) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def _rule_per_cell(column: np.ndarray, threshold: float | None, probs: bool) -> int | None:
    # The conventions' rule spelled out for one cell with plain Python, as the reference; None where 1 - p(empty) is
    # within rounding of the threshold and either answer is right.
    values = [float(v) for v in column]
    best = max(range(1, len(values)), key=lambda c: (values[c], -c))
    if threshold is None:
        return best if values[best] > values[0] else 0
    p = values if probs else list(_softmax(np.array(values), 0))
    if abs(1.0 - p[0] - threshold) < 1e-12:
        return None
    return best if 1.0 - p[0] >= threshold else 0


@FAST
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(2, 7), st.integers(1, 4), st.integers(1, 4)),
               elements=st.floats(-6, 6, width=16)),
    st.one_of(st.none(), st.floats(0.0, 1.0)),
    st.booleans(),
)
def test_labels_from_scores_matches_the_rule_cell_by_cell(scores: np.ndarray, threshold, probs: bool) -> None:
    if probs:
        scores = _softmax(scores, 0)
    out = labels_from_scores(scores, threshold=threshold, probs=probs)
    assert out.shape == scores.shape[1:] and out.dtype == np.uint8
    for idx in np.ndindex(*scores.shape[1:]):
        expected = _rule_per_cell(scores[(slice(None), *idx)], threshold, probs)
        assert expected is None or out[idx] == expected, idx


def test_threshold_rule_examples() -> None:
    # Two cells, 3 classes, probabilities: p(empty) = 0.6 and 0.2.
    p = np.array([[0.6, 0.2], [0.1, 0.5], [0.3, 0.3]])
    assert labels_from_scores(p, probs=True).tolist() == [0, 1]
    assert labels_from_scores(p, threshold=0.35, probs=True).tolist() == [2, 1]
    assert labels_from_scores(p, threshold=0.5, probs=True).tolist() == [0, 1]
    logits = np.log(p)
    assert labels_from_scores(logits, threshold=0.35).tolist() == [2, 1]
    assert labels_from_scores(logits, threshold=0.45).tolist() == [0, 1]
    # Ties: empty wins a tie with a non-empty class under argmax; among non-empty classes the lowest wins.
    tie = np.array([[1.0, 0.0], [1.0, 2.0], [0.0, 2.0]])
    assert labels_from_scores(tie).tolist() == [0, 1]


def test_labels_from_scores_axis_and_batches() -> None:
    rng = np.random.default_rng(3)
    logits = rng.normal(size=(2, 7, 4, 5, 6)).astype(np.float32)
    batched = labels_from_scores(logits, threshold=0.3, axis=1)
    assert batched.shape == (2, 4, 5, 6)
    for b in range(2):
        np.testing.assert_array_equal(batched[b], labels_from_scores(logits[b], threshold=0.3))
    last = labels_from_scores(np.moveaxis(logits, 1, -1), axis=-1)
    np.testing.assert_array_equal(last, labels_from_scores(logits, axis=1))


def test_softmax_threshold_is_stable_for_large_logits() -> None:
    # p(empty) = 1 / (1 + e^-40) rounds to 1.0 in float64, yet 1 - p(empty) = e^-40 is far from 0.
    scores = np.array([[40.0], [0.0]])
    assert labels_from_scores(scores, threshold=1e-18).tolist() == [1]
    assert labels_from_scores(scores, threshold=1e-17).tolist() == [0]


@pytest.mark.parametrize(
    "scores, kwargs",
    [
        (np.array([[np.nan, 0.0], [1.0, 2.0]]), {}),
        (np.array([[np.inf, 0.0], [1.0, 2.0]]), {"threshold": 0.5}),
        (np.array([[0.5, 1.5], [0.5, -0.5]]), {"probs": True, "threshold": 0.5}),
        (np.zeros((3, 2)), {"threshold": 1.5}),
        (np.zeros((3, 2)), {"threshold": "x"}),
        (np.zeros((3, 2)), {"axis": 2}),
        (np.zeros((257, 1)), {}),
        (np.array(["a", "b"]), {}),
        (np.float64(1.0), {}),
    ],
)
def test_labels_from_scores_refuses_bad_input(scores, kwargs) -> None:
    with pytest.raises(ValueError):
        labels_from_scores(scores, **kwargs)


# ---------------------------------------------------------------------------------------------------- the model
def test_model_validates_and_freezes_labels() -> None:
    lab = _random_labels(1).astype(np.int64)
    m = FruxelModel(lab, GRID)
    assert m.labels.dtype == np.uint8 and m.labels.shape == GRID.shape and m.classes == DEFAULT_CLASSES
    lab[0, 0, 0] = 3
    assert m.labels[0, 0, 0] == _random_labels(1)[0, 0, 0], "the model must hold its own copy"
    with pytest.raises(ValueError):
        m.labels[0, 0, 0] = 1
    for bad in (np.zeros((4, 5, 5), np.uint8), np.full(GRID.shape, 7, np.uint8), np.full(GRID.shape, -1),
                np.zeros(GRID.shape, np.float32)):
        with pytest.raises(ModelError):
            FruxelModel(bad, GRID)
    with pytest.raises(ModelError):
        FruxelModel(np.zeros(GRID.shape, np.uint8), GRID, classes=("empty", "wall"))


def test_occupied_counts_and_equality() -> None:
    lab = _random_labels(2)
    m = FruxelModel(lab, GRID)
    np.testing.assert_array_equal(m.occupied, lab > 0)
    assert m.n_occupied == int((lab > 0).sum())
    counts = m.counts()
    assert counts.shape == (7,) and counts.sum() == GRID.n_cells
    assert [int((lab == c).sum()) for c in range(7)] == counts.tolist()
    assert m == FruxelModel(lab.copy(), GRID)
    other = lab.copy()
    other[0, 0, 0] = (other[0, 0, 0] + 1) % 7
    assert m != FruxelModel(other, GRID)
    assert m != FruxelModel(lab, GRID, DEFAULT_CLASSES.extended("x"))
    assert FruxelModel.empty(GRID).n_occupied == 0
    assert m.colours().shape == GRID.shape + (3,)


def test_from_array_accepts_labels_and_scores() -> None:
    lab = _random_labels(4)
    assert FruxelModel.from_array(lab.astype(np.int32), GRID).labels.tolist() == lab.tolist()
    # Logits whose argmax is the label, float32 and float16, with and without the batch axis.
    onehot = np.moveaxis(np.eye(7)[lab], -1, 0) * 5.0
    for arr in (onehot.astype(np.float32), onehot[None].astype(np.float16)):
        np.testing.assert_array_equal(FruxelModel.from_array(arr, GRID).labels, lab)
    probs = _softmax(onehot, 0)
    np.testing.assert_array_equal(
        FruxelModel.from_array(probs, GRID, threshold=0.99, probs=True).labels,
        labels_from_scores(probs, threshold=0.99, probs=True),
    )


@pytest.mark.parametrize(
    "array, kwargs",
    [
        (np.zeros((1,) + GRID.shape, np.uint8), {}),
        (np.zeros(GRID.shape, np.uint8), {"threshold": 0.5}),
        (np.zeros((6,) + GRID.shape, np.float32), {}),
        (np.zeros((7, 4, 5, 5), np.float32), {}),
        (np.zeros((2, 7) + GRID.shape, np.float32), {}),
        (np.zeros(GRID.shape, bool), {}),
        (np.full((7,) + GRID.shape, np.nan, np.float32), {}),
        (np.full((7,) + GRID.shape, np.inf, np.float64), {"threshold": 0.5}),
    ],
)
def test_from_array_refuses_bad_input(array, kwargs) -> None:
    with pytest.raises(ValueError):
        FruxelModel.from_array(array, GRID, **kwargs)


# ---------------------------------------------------------------------------------------------------- points
def test_to_points_gives_centres_and_labels_of_occupied_cells() -> None:
    m = FruxelModel(_random_labels(5), GRID)
    pts, lab = m.to_points()
    assert pts.shape == (m.n_occupied, 3) and pts.dtype == np.float64 and lab.dtype == np.uint8
    k, j, i = GRID.point_to_cell(pts).T
    np.testing.assert_array_equal(m.labels[k, j, i], lab)
    assert np.all(lab > 0)
    np.testing.assert_allclose(pts, GRID.cell_to_point(k, j, i))
    assert FruxelModel.from_points(pts, lab, GRID) == m


def test_from_points_majority_rule() -> None:
    c = GRID.cell_to_point(1, 2, 3)
    d = GRID.cell_to_point(3, 0, 0)
    e = GRID.cell_to_point(0, 4, 5)
    points = np.array([c, c, c, c, d, d, e, e, e, [0.0, 0.0, -1.0]])
    labels = np.array([4, 2, 4, 0, 5, 3, 0, 0, 6, 1])
    m = FruxelModel.from_points(points, labels, GRID)
    assert m.labels[1, 2, 3] == 4  # majority
    assert m.labels[3, 0, 0] == 3  # tie goes to the lowest label
    assert m.labels[0, 4, 5] == 6  # label-0 points do not vote
    assert m.n_occupied == 3  # the point behind the camera is dropped
    empty = FruxelModel.from_points(np.zeros((0, 3)), np.zeros(0, np.uint8), GRID)
    assert empty.n_occupied == 0


@pytest.mark.parametrize(
    "points, labels",
    [
        (np.zeros((3, 2)), np.zeros(3, int)),
        (np.zeros((3, 3)), np.zeros(2, int)),
        (np.full((1, 3), np.nan), np.ones(1, int)),
        (np.ones((1, 3)), np.array([9])),
        (np.ones((1, 3)), np.array([1.0])),
    ],
)
def test_from_points_refuses_bad_input(points, labels) -> None:
    with pytest.raises(ModelError):
        FruxelModel.from_points(points, labels, GRID)


# ---------------------------------------------------------------------------------------------------- Cartesian
def test_to_cartesian_labels_voxels_by_their_centre() -> None:
    m = FruxelModel(_random_labels(6), GRID)
    lo, hi = GRID.bounds()
    size = np.array([0.21, 0.17, 0.23])
    origin = lo - 0.3
    shape = tuple(int(s) for s in np.ceil((hi - origin + 0.3) / size)[::-1])
    cart = m.to_cartesian(origin, size, shape)
    assert cart.shape == shape and cart.dtype == np.uint8
    z, y, x = np.meshgrid(*(np.arange(s) for s in shape), indexing="ij")
    centres = origin + (np.stack([x, y, z], axis=-1) + 0.5) * size
    cells = GRID.point_to_cell(centres)
    inside = cells[..., 0] >= 0
    expected = np.zeros(shape, np.uint8)
    expected[inside] = m.labels[cells[inside, 0], cells[inside, 1], cells[inside, 2]]
    np.testing.assert_array_equal(cart, expected)
    assert 0 < np.count_nonzero(cart) and cart[0, 0, 0] == 0


def test_cartesian_axis_order_and_origin_convention() -> None:
    # 2 x 2 x 2 cells with z in [1, 3), u and v in [-1, 1); a Cartesian grid of 2 x 2 x 2 voxels whose minimum
    # corner is (-2, -2, 1) with voxels (2, 2, 1) m puts each cell centre in voxel [z=k, y=j, x=i].
    grid = FruxelGrid(width=2, height=2, depth=2, z_near=1.0, z_far=3.0, hfov=90.0)
    classes = ClassTable.from_names([f"c{n}" for n in range(1, 9)])
    z, y, x = np.meshgrid(np.arange(2), np.arange(2), np.arange(2), indexing="ij")
    cart = (1 + x + 2 * y + 4 * z).astype(np.uint8)
    m = FruxelModel.from_cartesian(cart, (-2.0, -2.0, 1.0), (2.0, 2.0, 1.0), grid, classes)
    k, j, i = np.meshgrid(np.arange(2), np.arange(2), np.arange(2), indexing="ij")
    np.testing.assert_array_equal(m.labels, 1 + i + 2 * j + 4 * k)
    # The other way, one line of voxels along each axis, each centre picked inside a known cell.
    lab = np.zeros(grid.shape, np.uint8)
    lab[1, 0, 0], lab[1, 0, 1], lab[0, 1, 1], lab[1, 1, 1], lab[0, 0, 1] = 2, 4, 1, 5, 3
    m = FruxelModel(lab, grid)
    # x: centres (-0.5, -0.5, 2.75) in cell (1, 0, 0) and (0.5, -0.5, 2.75) in cell (1, 0, 1).
    assert m.to_cartesian((-1.0, -1.0, 2.25), 1.0, (1, 1, 2)).tolist() == [[[2, 4]]]
    # z: centres (0.6, 0.6, 1.5) in cell (0, 1, 1) and (0.6, 0.6, 2.5) in cell (1, 1, 1).
    assert m.to_cartesian((0.1, 0.1, 1.0), 1.0, (2, 1, 1)).tolist() == [[[1]], [[5]]]
    # y: centres (0.6, -0.5, 1.5) in cell (0, 0, 1) and (0.6, 0.5, 1.5) in cell (0, 1, 1).
    assert m.to_cartesian((0.1, -1.0, 1.0), 1.0, (1, 2, 1)).tolist() == [[[3], [1]]]


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**16))
def test_cartesian_round_trip_at_fine_resolution(seed: int) -> None:
    # A Cartesian grid much finer than the cells gives back every cell whose centre's voxel lies in that cell.
    grid = FruxelGrid(width=4, height=3, depth=3, z_near=1.0, z_far=2.5, hfov=60.0)
    m = FruxelModel(_random_labels(seed, grid), grid)
    lo, hi = grid.bounds()
    size = 0.05
    shape = tuple(int(s) for s in np.ceil((hi - lo) / size)[::-1] + 1)
    back = FruxelModel.from_cartesian(m.to_cartesian(lo, size, shape), lo, size, grid)
    assert back == m


def test_from_cartesian_outside_is_empty_and_validates() -> None:
    cart = np.full((2, 2, 2), 3, np.uint8)
    m = FruxelModel.from_cartesian(cart, (100.0, 100.0, 100.0), 1.0, GRID)
    assert m.n_occupied == 0
    with pytest.raises(ModelError):
        FruxelModel.from_cartesian(np.zeros((2, 2)), (0, 0, 0), 1.0, GRID)
    with pytest.raises(ModelError):
        FruxelModel.from_cartesian(np.full((2, 2, 2), 9), (0, 0, 0), 1.0, GRID)
    with pytest.raises(ModelError):
        FruxelModel.from_cartesian(cart, (0, 0), 1.0, GRID)
    with pytest.raises(ModelError):
        FruxelModel.from_cartesian(cart, (0, 0, 0), 0.0, GRID)
    with pytest.raises(ModelError):
        FruxelModel(_random_labels(0), GRID).to_cartesian((0, 0, 0), 1.0, (2, 2))
