"""Tests of fruxel.mesh: closedness, face counts, areas, volumes, colours and export of the three modes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fruxel import FruxelGrid
from fruxel import mesh as fmesh
from fruxel.mesh import MODES, TriMesh, export_mesh, mesh_labels, to_trimesh

trimesh = pytest.importorskip("trimesh")

PALETTE = np.array([[0, 0, 0], [200, 40, 40], [40, 200, 40], [40, 40, 200], [220, 220, 30]], dtype=np.uint8)


# ---------------------------------------------------------------------------- helpers
def signed_volume(mesh: TriMesh) -> float:
    """Volume enclosed by the mesh by the divergence theorem (sum of signed tetrahedra to the origin), m^3."""
    v = mesh.vertices.astype(np.float64)[mesh.faces]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def occupied_volume(labels: np.ndarray, grid: FruxelGrid) -> float:
    return float((grid.cell_volumes() * (labels != 0)).sum())


def boundary_face_count(labels: np.ndarray) -> int:
    """Faces between an occupied cell and an empty one or the outside, counted from occupancy changes."""
    occ = np.pad(labels != 0, 1).astype(np.int8)
    return int(sum(np.count_nonzero(np.diff(occ, axis=a)) for a in range(3)))


def directed_edges_balanced(faces: np.ndarray) -> bool:
    """True when every directed edge (a, b) occurs exactly as often as (b, a): a closed, consistently wound
    surface, also where four faces meet at one edge."""
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    n = int(faces.max()) + 1
    fwd = np.sort(e[:, 0] * n + e[:, 1])
    rev = np.sort(e[:, 1] * n + e[:, 0])
    return bool(np.array_equal(fwd, rev))


def merge_by_position(mesh: TriMesh) -> np.ndarray:
    """Faces re-indexed so that vertices with identical coordinates share one index: ``(F, 3)`` int64."""
    _, inv = np.unique(mesh.vertices, axis=0, return_inverse=True)
    return inv.reshape(-1)[mesh.faces]


def area_by_group(mesh: TriMesh) -> dict[tuple[int, int, int], float]:
    """Triangle area summed per (class, plane family, facing sign).

    Families come from the triangle's normal: z-planes have normal (0, 0, +-1), u-planes ``x = u z`` have no
    y component, v-planes ``y = v z`` no x component.
    """
    v = mesh.vertices.astype(np.float64)[mesh.faces]
    cr = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = 0.5 * np.linalg.norm(cr, axis=1)
    n = cr / (2.0 * area[:, None])
    fam = np.where(
        (np.abs(n[:, 0]) < 1e-4) & (np.abs(n[:, 1]) < 1e-4), 2, np.where(np.abs(n[:, 1]) < 1e-4, 0, 1)
    )
    assert np.all((fam != 2) | (np.abs(n[:, 2]) > 0.999))
    assert np.all((fam != 0) | (np.abs(n[:, 0]) > 1e-3))
    assert np.all((fam != 1) | ((np.abs(n[:, 0]) < 1e-4) & (np.abs(n[:, 1]) > 1e-3)))
    sign = np.sign(n[np.arange(len(n)), fam]).astype(int)
    out: dict[tuple[int, int, int], float] = {}
    for key, a in zip(zip(mesh.labels.tolist(), fam.tolist(), sign.tolist(), strict=True), area, strict=True):
        out[key] = out.get(key, 0.0) + float(a)
    return out


def own_view_shell(labels: np.ndarray) -> np.ndarray:
    """The VMS shell from the grid's own camera (conventions section 4): the first occupied cell of each column."""
    occ = labels != 0
    k = occ.argmax(axis=0)
    jj, ii = np.nonzero(occ.any(axis=0))
    out = np.zeros_like(labels)
    out[k[jj, ii], jj, ii] = labels[k[jj, ii], jj, ii]
    return out


def canonical_triangles(mesh: TriMesh) -> list[tuple]:
    """Triangles as (label, vertex coordinates) with the smallest vertex first, keeping the winding: sorted."""
    tri = mesh.vertices[mesh.faces].astype(np.float64).tolist()
    out = []
    for lab, t in zip(mesh.labels.tolist(), tri, strict=True):
        r = min(range(3), key=lambda q: t[q])
        out.append((lab, tuple(map(tuple, t[r:] + t[:r]))))
    return sorted(out)


def culled_from_full(full: TriMesh) -> list[tuple]:
    """The culled surface derived from the full mesh: the hexahedra's triangles whose reverse (the same
    triangle of the neighbouring cell, wound the other way) is not in the mesh."""
    tris = canonical_triangles(full)
    positions = {t for _, t in tris}
    return sorted((lab, t) for lab, t in tris if (t[0], t[2], t[1]) not in positions)


def unit_faces(mesh: TriMesh, grid: FruxelGrid) -> list[tuple[int, int, int, int, int, int]]:
    """Every quad of a culled or greedy mesh split back into cell faces, in index space: sorted
    ``(label, normal array axis, plane index, facing sign, first index, second index)``, one per cell face.

    Vertices are mapped back to their lattice indices by exact coordinates; two consecutive triangles make one
    quad. Equal lists mean the same faces with no overlap and no gap.
    """
    kb, jb, ib = np.meshgrid(np.arange(grid.depth + 1), np.arange(grid.height + 1), np.arange(grid.width + 1),
                             indexing="ij")
    pts = grid.corner_points(kb, jb, ib).astype(np.float32).reshape(-1, 3)
    index_of = {tuple(p): idx for p, idx in zip(pts.tolist(), np.stack([kb, jb, ib], -1).reshape(-1, 3).tolist(),
                                                strict=True)}
    assert len(index_of) == len(pts), "lattice points must be distinct"
    lattice = np.array([index_of[tuple(v)] for v in mesh.vertices.tolist()], np.int64).reshape(-1, 3)
    out = []
    for q in range(mesh.n_faces // 2):
        corners = lattice[mesh.faces[2 * q : 2 * q + 2].reshape(-1)]
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        flat_axes = np.flatnonzero(lo == hi)
        assert flat_axes.size == 1, "a quad lies on one grid plane"
        a = int(flat_axes[0])
        b, c = (x for x in range(3) if x != a)
        t = lattice[mesh.faces[2 * q]]
        # The index space -> grid frame map keeps orientation, so the winding in index space gives the facing.
        # (k, j, i) is a left-handed order of the xyz axes, hence the minus sign.
        facing = -int(np.sign(np.cross(t[1] - t[0], t[2] - t[0])[a]))
        for x in range(lo[b], hi[b]):
            for y in range(lo[c], hi[c]):
                out.append((int(mesh.labels[2 * q]), a, int(lo[a]), facing, x, y))
    return sorted(out)


@st.composite
def volumes(draw, max_class: int = 4):
    w, h, d = draw(st.integers(1, 5)), draw(st.integers(1, 5)), draw(st.integers(1, 5))
    z_near = draw(st.floats(0.2, 2.0))
    grid = FruxelGrid(width=w, height=h, depth=d, z_near=z_near, z_far=z_near + draw(st.floats(0.2, 5.0)),
                      hfov=draw(st.floats(20.0, 140.0)))
    labels = draw(hnp.arrays(np.uint8, grid.shape, elements=st.integers(0, max_class)))
    return labels, grid


FAST = settings(max_examples=60, deadline=None)


# ---------------------------------------------------------------------------- one cell
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("cell", [(0, 0, 0), (2, 1, 3), (4, 2, 0)])
def test_single_cell_is_closed_with_cell_volume(mode, cell):
    grid = FruxelGrid(width=4, height=3, depth=5, z_near=0.5, z_far=3.0, hfov=70.0)
    labels = np.zeros(grid.shape, np.uint8)
    labels[cell] = 3
    m = mesh_labels(labels, grid, PALETTE, mode)
    assert (m.n_vertices, m.n_faces) == (8, 12)
    tm = to_trimesh(m)
    assert tm.is_watertight
    assert tm.is_winding_consistent
    assert tm.volume == pytest.approx(grid.slice_volumes()[cell[0]], rel=1e-5)
    assert tm.volume > 0, "normals must point outwards"
    np.testing.assert_array_equal(
        np.sort(m.vertices, axis=0), np.sort(grid.cell_corners(*cell).astype(np.float32), axis=0)
    )


def test_full_vertices_are_bit_identical_to_corner_points():
    grid = FruxelGrid(width=7, height=5, depth=6, z_near=0.3, z_far=4.1, hfov=83.0)
    labels = np.random.default_rng(3).integers(0, 3, grid.shape).astype(np.uint8)
    m = mesh_labels(labels, grid, PALETTE, "full")
    k, j, i = np.nonzero(labels)
    expected = grid.cell_corners(k, j, i).astype(np.float32).reshape(-1, 3)
    np.testing.assert_array_equal(m.vertices, expected)
    for mode in ("culled", "greedy"):
        other = mesh_labels(labels, grid, PALETTE, mode)
        assert set(map(tuple, other.vertices.tolist())) <= set(map(tuple, m.vertices.tolist()))


# ---------------------------------------------------------------------------- random volumes
@FAST
@given(volumes())
def test_culled_face_count_matches_occupancy_changes(vol):
    labels, grid = vol
    m = mesh_labels(labels, grid, PALETTE, "culled")
    assert m.n_faces == 2 * boundary_face_count(labels)


@FAST
@given(volumes())
def test_greedy_covers_the_culled_area_per_class_and_plane_family(vol):
    labels, grid = vol
    culled = area_by_group(mesh_labels(labels, grid, PALETTE, "culled"))
    greedy = area_by_group(mesh_labels(labels, grid, PALETTE, "greedy"))
    assert culled.keys() == greedy.keys()
    for key, a in culled.items():
        assert greedy[key] == pytest.approx(a, rel=1e-5, abs=1e-9), key


@FAST
@given(volumes())
def test_all_modes_closed_with_occupied_volume(vol):
    labels, grid = vol
    expected = occupied_volume(labels, grid)
    full = mesh_labels(labels, grid, PALETTE, "full")
    culled = mesh_labels(labels, grid, PALETTE, "culled")
    greedy = mesh_labels(labels, grid, PALETTE, "greedy")
    n = int(np.count_nonzero(labels))
    assert full.n_faces == 12 * n and full.n_vertices == 8 * n
    if n == 0:
        assert culled.n_faces == greedy.n_faces == 0
        return
    # Full: hexahedra share nothing, so each must be closed on its own 8 vertices.
    assert np.array_equal(full.faces // 8, np.repeat(np.arange(n), 12)[:, None].repeat(3, axis=1))
    assert directed_edges_balanced(full.faces)
    # Culled: vertices are duplicated per class, so the surface is closed once they are merged by position.
    assert directed_edges_balanced(merge_by_position(culled))
    assert greedy.n_faces <= culled.n_faces
    for m in (full, culled, greedy):
        assert signed_volume(m) == pytest.approx(expected, rel=2e-5)
        tri = merge_by_position(m)
        assert np.all((tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2]))


@FAST
@given(volumes())
def test_colours_and_labels_follow_the_cell_class(vol):
    labels, grid = vol
    for mode in MODES:
        m = mesh_labels(labels, grid, PALETTE, mode)
        assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32
        assert m.colors.dtype == np.uint8 and m.labels.dtype == np.uint8
        assert m.colors.shape == (m.n_vertices, 4) and m.labels.shape == (m.n_faces,)
        assert np.all(m.labels != 0)
        # No colour bleeding: all three vertices of a face carry the face's class colour.
        np.testing.assert_array_equal(m.colors[m.faces][:, :, :3], np.repeat(PALETTE[m.labels][:, None], 3, axis=1))
        assert np.all(m.colors[:, 3] == 255)
        counts = np.bincount(m.labels, minlength=len(PALETTE))
        present = np.bincount(labels.reshape(-1), minlength=len(PALETTE)) > 0
        if mode == "full":
            assert np.array_equal(counts[1:] > 0, present[1:])
        else:
            # A class may be buried inside other occupied cells and then has no face on the surface.
            assert not np.any((counts > 0) & ~present)


def test_culled_keeps_no_face_between_two_occupied_classes():
    grid = FruxelGrid(width=3, height=1, depth=1, z_near=1.0, z_far=2.0, hfov=60.0)
    labels = np.array([[[1, 2, 0]]], np.uint8)
    m = mesh_labels(labels, grid, PALETTE, "culled")
    assert m.n_faces == 2 * 10
    # Per-class vertex copies: the shared quad's 4 lattice points appear once per class.
    assert m.n_vertices == 16
    assert np.bincount(m.labels).tolist() == [0, 10, 10]


def test_greedy_merges_a_full_block_into_six_quads():
    grid = FruxelGrid(width=9, height=6, depth=11, z_near=0.5, z_far=6.0, hfov=60.0)
    labels = np.full(grid.shape, 2, np.uint8)
    m = mesh_labels(labels, grid, PALETTE, "greedy")
    assert m.n_faces == 12 and m.n_vertices == 8
    tm = to_trimesh(m)
    assert tm.is_watertight and tm.is_winding_consistent
    assert tm.volume == pytest.approx(occupied_volume(labels, grid), rel=1e-5)


def test_greedy_merges_a_slab_with_a_hole():
    grid = FruxelGrid(width=8, height=8, depth=4, z_near=1.0, z_far=3.0, hfov=50.0)
    labels = np.zeros(grid.shape, np.uint8)
    labels[1] = 1
    labels[1, 3:5, 3:5] = 0
    culled = mesh_labels(labels, grid, PALETTE, "culled")
    greedy = mesh_labels(labels, grid, PALETTE, "greedy")
    assert culled.n_faces == 2 * (2 * (64 - 4) + 4 * 8 + 4 * 2)
    # Front and back: the rows above and below the hole and the two runs beside it, 4 rectangles each; the
    # outer sides and the hole's walls one rectangle each.
    assert greedy.n_faces == 2 * (2 * 4 + 4 + 4)
    assert signed_volume(greedy) == pytest.approx(occupied_volume(labels, grid), rel=1e-5)


def test_dense_and_sorted_vertex_keys_agree(monkeypatch):
    grid = FruxelGrid(width=6, height=5, depth=4, z_near=0.5, z_far=2.0, hfov=60.0)
    labels = np.random.default_rng(7).integers(0, 5, grid.shape).astype(np.uint8)
    dense = mesh_labels(labels, grid, PALETTE, "culled")
    monkeypatch.setattr(fmesh, "_DENSE_KEY_LIMIT", 0)
    sorted_keys = mesh_labels(labels, grid, PALETTE, "culled")
    for a, b in ((dense.vertices, sorted_keys.vertices), (dense.faces, sorted_keys.faces),
                 (dense.colors, sorted_keys.colors), (dense.labels, sorted_keys.labels)):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------- exact faces, sparse shells
def sparse_cases() -> list:
    """Sparse inputs of the interactive path (own-view shells) and cells on the grid's edges and corners."""
    rng = np.random.default_rng(5)
    grid = FruxelGrid(width=9, height=7, depth=8, z_near=0.4, z_far=3.5, hfov=75.0)
    cases = []
    solid = rng.integers(0, 5, grid.shape).astype(np.uint8) * (rng.random(grid.shape) < 0.3)
    cases.append(("shell of random cells", own_view_shell(solid), grid))
    blocks = np.zeros(grid.shape, np.uint8)
    blocks[5:, :, :] = 2
    blocks[3:, 4:, 2:6] = 1
    blocks[2, 1:3, 0] = 4
    cases.append(("shell of blocks", own_view_shell(blocks), grid))
    corners = np.zeros(grid.shape, np.uint8)
    for k in (0, -1):
        for j in (0, -1):
            for i in (0, -1):
                corners[k, j, i] = 1 + (k + j + i) % 4
    corners[3, 0, :] = 3
    corners[4, :, -1] = 2
    cases.append(("grid corners and edges", corners, grid))
    far = np.zeros(grid.shape, np.uint8)
    far[-2:, 2:5, 3] = 1
    cases.append(("last slices only", far, grid))
    line = FruxelGrid(width=1, height=1, depth=6, z_near=0.5, z_far=2.0, hfov=40.0)
    cases.append(("one column", np.array([0, 1, 1, 2, 0, 1], np.uint8).reshape(line.shape), line))
    row = FruxelGrid(width=7, height=1, depth=1, z_near=0.5, z_far=2.0, hfov=40.0)
    cases.append(("one row", np.array([1, 1, 0, 2, 2, 2, 1], np.uint8).reshape(row.shape), row))
    return [pytest.param(labels, grid, id=name) for name, labels, grid in cases]


@pytest.mark.parametrize("labels, grid", sparse_cases())
def test_culled_faces_are_the_full_mesh_without_shared_faces(labels, grid):
    full = mesh_labels(labels, grid, PALETTE, "full")
    culled = mesh_labels(labels, grid, PALETTE, "culled")
    assert canonical_triangles(culled) == culled_from_full(full)


@pytest.mark.parametrize("labels, grid", sparse_cases())
def test_greedy_rectangles_tile_exactly_the_culled_faces(labels, grid):
    culled = mesh_labels(labels, grid, PALETTE, "culled")
    greedy = mesh_labels(labels, grid, PALETTE, "greedy")
    assert unit_faces(greedy, grid) == unit_faces(culled, grid)
    assert greedy.n_faces <= culled.n_faces
    assert signed_volume(greedy) == pytest.approx(occupied_volume(labels, grid), rel=1e-5)


@FAST
@given(volumes())
def test_sparse_shell_meshes_are_exact(vol):
    labels, grid = vol
    shell = own_view_shell(labels)
    full = mesh_labels(shell, grid, PALETTE, "full")
    culled = mesh_labels(shell, grid, PALETTE, "culled")
    greedy = mesh_labels(shell, grid, PALETTE, "greedy")
    assert canonical_triangles(culled) == culled_from_full(full)
    assert unit_faces(greedy, grid) == unit_faces(culled, grid)


def test_full_vertices_of_a_sparse_volume_are_bit_identical_to_corner_points():
    grid = FruxelGrid(width=6, height=5, depth=9, z_near=0.7, z_far=5.3, hfov=95.0)
    labels = np.zeros(grid.shape, np.uint8)
    labels[4, 0, 5] = 1
    labels[6, 4, 0] = 2
    labels[8, 2, 3] = 3
    m = mesh_labels(labels, grid, PALETTE, "full")
    k, j, i = np.nonzero(labels)
    np.testing.assert_array_equal(m.vertices, grid.cell_corners(k, j, i).astype(np.float32).reshape(-1, 3))


@pytest.mark.parametrize("mode", ["culled", "greedy"])
@pytest.mark.parametrize("path", ["sorted", "unique"])
def test_vertex_key_paths_agree(monkeypatch, mode, path):
    grid = FruxelGrid(width=7, height=6, depth=5, z_near=0.5, z_far=2.0, hfov=60.0)
    labels = own_view_shell(np.random.default_rng(9).integers(0, 5, grid.shape).astype(np.uint8))
    dense = mesh_labels(labels, grid, PALETTE, mode)
    monkeypatch.setattr(fmesh, "_DENSE_KEY_LIMIT", 0)
    if path == "unique":
        # Too few bits to pack key and position: the de-duplication falls back to np.unique.
        monkeypatch.setattr(fmesh, "_SORT_KEY_BITS", 0)
    other = mesh_labels(labels, grid, PALETTE, mode)
    for a, b in ((dense.vertices, other.vertices), (dense.faces, other.faces),
                 (dense.colors, other.colors), (dense.labels, other.labels)):
        np.testing.assert_array_equal(a, b)



@pytest.mark.parametrize("mode", ["culled", "greedy"])
def test_sparse_and_dense_face_search_agree(monkeypatch, mode):
    grid = FruxelGrid(width=8, height=7, depth=6, z_near=0.5, z_far=2.5, hfov=60.0)
    rng = np.random.default_rng(13)
    for labels in (rng.integers(0, 5, grid.shape).astype(np.uint8),
                   own_view_shell(rng.integers(0, 5, grid.shape).astype(np.uint8) * (rng.random(grid.shape) < 0.2))):
        meshes = []
        # Factor 0 always looks up the occupied cells' neighbours; a huge one always uses whole-grid masks.
        for factor in (0, 10**9):
            monkeypatch.setattr(fmesh, "_SPARSE_FACES_FACTOR", factor)
            meshes.append(mesh_labels(labels, grid, PALETTE, mode))
        for field in ("vertices", "faces", "colors", "labels"):
            np.testing.assert_array_equal(getattr(meshes[0], field), getattr(meshes[1], field))

def test_empty_volume_gives_empty_mesh():
    grid = FruxelGrid(width=3, height=3, depth=3, z_near=0.5, z_far=2.0, hfov=60.0)
    for mode in MODES:
        m = mesh_labels(np.zeros(grid.shape, np.uint8), grid, PALETTE, mode)
        assert m.vertices.shape == (0, 3) and m.faces.shape == (0, 3)
        assert m.colors.shape == (0, 4) and m.labels.shape == (0,)


def test_bad_input_is_refused():
    grid = FruxelGrid(width=3, height=3, depth=3, z_near=0.5, z_far=2.0, hfov=60.0)
    ok = np.zeros(grid.shape, np.uint8)
    with pytest.raises(ValueError, match="mode"):
        mesh_labels(ok, grid, PALETTE, "smooth")
    with pytest.raises(ValueError, match="shape"):
        mesh_labels(np.zeros((3, 3, 4), np.uint8), grid, PALETTE)
    with pytest.raises(ValueError, match="integer"):
        mesh_labels(ok.astype(np.float32), grid, PALETTE)
    with pytest.raises(ValueError, match="range"):
        mesh_labels(np.full(grid.shape, len(PALETTE), np.uint8), grid, PALETTE)
    with pytest.raises(ValueError, match="uint8"):
        mesh_labels(ok, grid, PALETTE.astype(np.float32))
    with pytest.raises(ValueError, match="palette"):
        mesh_labels(ok, grid, PALETTE[:, :2])


# ---------------------------------------------------------------------------- export
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_export_round_trip(tmp_path, mode, suffix):
    grid = FruxelGrid(width=5, height=4, depth=6, z_near=0.5, z_far=3.0, hfov=60.0)
    labels = np.random.default_rng(11).integers(0, 5, grid.shape).astype(np.uint8)
    m = mesh_labels(labels, grid, PALETTE, mode)
    path = export_mesh(m, tmp_path / f"room{suffix}")
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"room{suffix}"], "no temporary file left behind"
    back = trimesh.load_mesh(path, process=False)
    assert back.vertices.shape == m.vertices.shape and back.faces.shape == m.faces.shape
    # PLY keeps the grid frame; glTF is +Y up: (x, y, z) -> (x, -y, -z), exactly.
    flip = np.float32([1, -1, -1]) if suffix == ".glb" else np.float32([1, 1, 1])
    np.testing.assert_array_equal(np.asarray(back.vertices, np.float32), m.vertices * flip)
    np.testing.assert_array_equal(back.faces, m.faces)
    np.testing.assert_array_equal(back.visual.vertex_colors, m.colors)
    if suffix == ".ply":
        np.testing.assert_array_equal(back.metadata["_ply_raw"]["face"]["data"]["label"], m.labels)


def test_glb_export_stands_upright(tmp_path):
    """glTF viewers take +Y as up: the sample room's floor is at the bottom and its walls rise above it, and the
    faces still wind counter-clockwise seen from outside (positive signed volume)."""
    from fruxel.data import SAMPLE_ROOM
    from fruxel.io import load

    model = load(SAMPLE_ROOM)
    m = mesh_labels(model.labels, model.grid, model.classes.palette(), "greedy")
    back = trimesh.load(export_mesh(m, tmp_path / "room.glb"), force="mesh", process=False)
    floor = np.all(back.visual.vertex_colors[:, :3] == model.classes.colours[model.classes.index("floor")], axis=1)
    wall = np.all(back.visual.vertex_colors[:, :3] == model.classes.colours[model.classes.index("wall")], axis=1)
    y = np.asarray(back.vertices)[:, 1]
    assert y[floor].max() < y[wall].mean() and y[wall].max() > y[floor].max() + 1.0
    assert back.volume > 0


def test_export_refuses_unknown_suffix_and_keeps_old_file(tmp_path):
    grid = FruxelGrid(width=2, height=2, depth=2, z_near=0.5, z_far=3.0, hfov=60.0)
    m = mesh_labels(np.ones(grid.shape, np.uint8), grid, PALETTE, "culled")
    with pytest.raises(ValueError, match="supports"):
        export_mesh(m, tmp_path / "room.obj")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------- bundled sample room
def test_sample_room_is_regenerated_exactly_and_greedy_is_10x_smaller():
    from fruxel.data import SAMPLE_ROOM
    from fruxel.data.make_sample import sample_model
    from fruxel.io import load

    model = load(SAMPLE_ROOM)
    assert model == sample_model(), "sample_room.npz is stale: run python scripts/make_sample.py"
    assert set(np.unique(model.labels).tolist()) == set(range(len(model.classes.names)))
    palette = model.classes.palette()
    culled = mesh_labels(model.labels, model.grid, palette, "culled")
    greedy = mesh_labels(model.labels, model.grid, palette, "greedy")
    assert culled.n_faces >= 10 * greedy.n_faces
    assert signed_volume(greedy) == pytest.approx(occupied_volume(model.labels, model.grid), rel=1e-5)
