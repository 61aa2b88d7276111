"""Tests of fruxel.render.scene: the OpenCV-to-pyrender camera conversion, agreement of pyrender images with
``first_hit``, shading of mesh faces, and the shared offscreen renderer."""

from __future__ import annotations

import numpy as np
import pytest

import fruxel
from fruxel import Camera, kernels
from fruxel.data import SAMPLE_ROOM
from fruxel.mesh import mesh_labels
from fruxel.render.frames import default_camera
from fruxel.render.raycast import RaycastStyle, first_hits, shade
from fruxel.render.scene import (
    MeshStyle,
    MeshView,
    clip_range,
    decode_labels,
    face_normals,
    pyrender_camera,
    render_mesh,
    renderers,
    vertex_arrays,
)

MODEL = fruxel.load(SAMPLE_ROOM)
PALETTE = MODEL.classes.palette()
BACKENDS = kernels.available_backends()


def cameras(width: int, height: int) -> list[Camera]:
    """Views of the sample room: the default oblique one, one from behind the far wall's left corner looking
    back, and one inside the frustum looking down at the floor."""
    g = MODEL.grid
    back = Camera.look_at((-3.0, -2.5, 9.0), g.centre(), width=width, height=height, hfov=55.0)
    inside = Camera.look_at((0.3, -0.5, 1.0), (0.0, 1.0, 4.0), width=width, height=height, hfov=70.0)
    return [default_camera(g, width, height), back, inside]


# ---------------------------------------------------------------------------------------------------- camera
@pytest.mark.parametrize("cam_index", [0, 1, 2])
def test_pyrender_projection_is_camera_project(cam_index: int) -> None:
    """pyrender's matrices put a grid point on the pixel and depth that Camera.project gives (OpenCV convention:
    pixel (x, y) covers [x, x + 1) x [y, y + 1), rows from the top)."""
    cam = cameras(200, 130)[cam_index]
    cam = Camera(fx=cam.fx * 1.1, fy=cam.fy, cx=cam.cx + 7.3, cy=cam.cy - 4.1, width=cam.width, height=cam.height,
                 pose=cam.pose)
    znear, zfar = clip_range(cam, MODEL.grid)
    P = pyrender_camera(cam, znear, zfar).get_projection_matrix(cam.width, cam.height)
    V = np.linalg.inv(cam.opengl_pose())
    pts = MODEL.grid.cell_centres().reshape(-1, 3)[::97]
    expected = cam.project(pts)
    pts, expected = pts[expected[:, 2] > znear], expected[expected[:, 2] > znear]
    clip = (P @ V @ np.c_[pts, np.ones(len(pts))].T).T
    ndc = clip[:, :3] / clip[:, 3:]
    x = (ndc[:, 0] + 1.0) / 2.0 * cam.width
    y = (1.0 - ndc[:, 1]) / 2.0 * cam.height  # read-back flips rows, so image row 0 is the window's top
    eye_z = -(V @ np.c_[pts, np.ones(len(pts))].T)[2]
    np.testing.assert_allclose(x, expected[:, 0], atol=1e-6 * cam.width)
    np.testing.assert_allclose(y, expected[:, 1], atol=1e-6 * cam.height)
    np.testing.assert_allclose(eye_z, expected[:, 2], rtol=1e-9)


def test_clip_range_holds_the_whole_frustum() -> None:
    for cam in cameras(64, 48):
        znear, zfar = clip_range(cam, MODEL.grid)
        p = cam.project(MODEL.grid.cell_centres().reshape(-1, 3))
        seen = (p[:, 2] > 0) & (p[:, 0] >= 0) & (p[:, 0] < cam.width) & (p[:, 1] >= 0) & (p[:, 1] < cam.height)
        assert 0 < znear < zfar
        assert p[seen, 2].min() > znear and p[seen, 2].max() < zfar


# ---------------------------------------------------------------------------------------------------- agreement
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("meshing", ["full", "greedy"])
def test_flat_mesh_image_agrees_with_first_hit(backend: str, meshing: str) -> None:
    """A flat-colour pyrender render of the mesh and first_hit's label image of the same camera agree on at
    least 99 % of the pixels (the rest are anti-aliased edges)."""
    mesh = mesh_labels(MODEL.labels, MODEL.grid, PALETTE, mode=meshing)
    for cam in cameras(160, 120):
        img = render_mesh(mesh, MODEL.grid, cam, MeshStyle(shading="flat"))
        drawn = decode_labels(img, PALETTE)
        hits = kernels.first_hit(MODEL.labels, MODEL.grid, cam, backend=backend)
        agree = float(np.mean(drawn == hits.label))
        assert agree >= 0.99, f"{agree:.4f} at {cam!r}"
        assert np.mean(hits.label != 0) > 0.2


def test_lit_mesh_image_matches_the_raycast_image_inside_faces() -> None:
    """Baked Lambert shading of the mesh and the ray-cast shading are one formula: away from face edges (where
    rasterisation and anti-aliasing legitimately differ from centre rays) the two images agree."""
    cam = cameras(160, 120)[0]
    mesh = mesh_labels(MODEL.labels, MODEL.grid, PALETTE, mode="culled")
    mimg = render_mesh(mesh, MODEL.grid, cam, MeshStyle(shading="lit")).astype(int)
    hits = first_hits(MODEL.labels, MODEL.grid, cam)
    rimg = shade(hits, cam, PALETTE, RaycastStyle(shading="lit")).astype(int)
    key = np.concatenate([np.asarray(hits.label)[..., None], np.round(np.asarray(hits.normal), 4)], axis=-1)
    pad = np.pad(key, ((1, 1), (1, 1), (0, 0)), mode="edge")
    inside = np.ones(key.shape[:2], bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            inside &= np.all(pad[dy:dy + key.shape[0], dx:dx + key.shape[1]] == key, axis=-1)
    assert inside.mean() > 0.5
    close = np.all(np.abs(mimg - rimg) <= 2, axis=-1)
    assert close[inside].mean() >= 0.99


# ---------------------------------------------------------------------------------------------------- meshes
def test_vertex_arrays_per_shading() -> None:
    mesh = mesh_labels(MODEL.labels, MODEL.grid, PALETTE, mode="greedy")
    pos, col, idx, nrm = vertex_arrays(mesh, MeshStyle(shading="flat"))
    assert idx is not None and nrm is None and pos.shape == (mesh.n_vertices, 3)
    np.testing.assert_allclose(col[:, :3] * 255.0, mesh.colors[:, :3], atol=1e-3)
    pos, col, idx, nrm = vertex_arrays(mesh, MeshStyle(shading="lit"), np.eye(3))
    assert idx is None and nrm is None and pos.shape == (3 * mesh.n_faces, 3) and col.shape == (3 * mesh.n_faces, 4)
    base = mesh.colors[mesh.faces[:, 0], :3] / 255.0
    ratio = col[::3, :3] / np.maximum(base, 1e-6)
    assert np.all(ratio[base > 0.05] <= 1.0 + 1e-5) and np.all(ratio[base > 0.05] >= MeshStyle().ambient - 1e-5)
    pos, col, idx, nrm = vertex_arrays(mesh, MeshStyle(shading="pbr"))
    assert nrm is not None and nrm.shape == pos.shape


def test_face_normals_point_out_of_a_cell() -> None:
    lab = np.zeros(MODEL.grid.shape, np.uint8)
    lab[10, 20, 30] = 1
    mesh = mesh_labels(lab, MODEL.grid, PALETTE, mode="full")
    centre = MODEL.grid.cell_to_point(10, 20, 30)
    tri_centres = mesh.vertices[mesh.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", face_normals(mesh), tri_centres - centre) > 0)
    np.testing.assert_allclose(np.linalg.norm(face_normals(mesh), axis=1), 1.0, rtol=1e-5)


def test_empty_mesh_draws_background() -> None:
    empty = mesh_labels(np.zeros(MODEL.grid.shape, np.uint8), MODEL.grid, PALETTE)
    img = render_mesh(empty, MODEL.grid, cameras(40, 30)[0])
    assert img.shape == (30, 40, 3) and np.all(img == 255)


def test_mesh_view_reuses_scene_and_renderer_across_sizes_and_meshes() -> None:
    view = MeshView(MODEL.grid, MeshStyle(shading="flat"))
    view.set_camera(cameras(80, 60)[0])
    view.set_mesh(mesh_labels(MODEL.labels, MODEL.grid, PALETTE, mode="greedy"))
    a = view.render()
    view.set_camera(cameras(50, 40)[0])
    b = view.render()
    lab = MODEL.labels.copy()
    lab[lab == MODEL.classes.index("furniture")] = 0
    view.set_mesh(mesh_labels(lab, MODEL.grid, PALETTE, mode="greedy"))
    view.upload()
    c = view.render()
    assert a.shape == (60, 80, 3) and b.shape == (40, 50, 3) and c.shape == (40, 50, 3)
    furniture = PALETTE[MODEL.classes.index("furniture")]
    assert np.any(np.all(b == furniture, axis=-1)) and not np.any(np.all(c == furniture, axis=-1))
    assert renderers().get(50, 40) is renderers().get(80, 60)


def test_decode_labels_round_trip() -> None:
    lab = np.arange(len(PALETTE)).repeat(3).reshape(1, -1)
    img = np.where((lab == 0)[..., None], 255, PALETTE[lab]).astype(np.uint8)
    assert np.array_equal(decode_labels(img, PALETTE), lab)


def test_mesh_style_validation() -> None:
    with pytest.raises(ValueError):
        MeshStyle(shading="glossy")
    with pytest.raises(ValueError):
        MeshStyle(ambient=1.5)


@pytest.mark.parametrize("cam_index", [0, 2])
def test_large_images_are_drawn_in_tiles_that_fit_together(cam_index: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """An image larger than one draw is drawn in tiles with moved principal points: it equals the image drawn at
    once but for rasterisation ties on a few edge pixels."""
    cam = cameras(100, 75)[cam_index]
    mesh = mesh_labels(MODEL.labels, MODEL.grid, PALETTE, "greedy")
    view = MeshView(MODEL.grid, MeshStyle(shading="lit", frustum=True))
    view.set_camera(cam)
    view.set_mesh(mesh)
    whole = view.render()
    monkeypatch.setattr(renderers(), "_max_side", 32)
    tiled = view.render()
    assert tiled.shape == whole.shape == (75, 100, 3)
    assert np.mean(np.any(tiled != whole, axis=-1)) < 0.005
    # The pyrender camera is left as it was.
    assert view._camera_node.camera.cx == cam.cx and view._camera_node.camera.cy == cam.cy
    monkeypatch.setattr(renderers(), "_max_side", None)
    assert renderers().max_side() >= 1024


def test_an_image_wider_than_opengl_allows() -> None:
    """17000 pixels is beyond GL_MAX_RENDERBUFFER_SIZE on Mesa (16384): drawn in tiles instead of a GLError."""
    g = MODEL.grid
    cam = Camera.look_at(g.centre() + np.array([0.0, -0.5, -9.0]), g.centre(), width=17000, height=24, hfov=120.0)
    img = render_mesh(mesh_labels(MODEL.labels, g, PALETTE, "greedy"), g, cam, MeshStyle(shading="flat"))
    assert img.shape == (24, 17000, 3)
    assert np.any(img != 255)
