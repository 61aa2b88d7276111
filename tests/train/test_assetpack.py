"""The asset pack: the real builder on the tiny committed sources (tests/data/assetpack_sources), its manifest,
licences, split, determinism, size budget, Sweet Home 3D rotations and the checked loader. No network."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from fruxel.train.sim.assetpack import AssetPack, AssetPackError
from fruxel.train.sim.assetpack.build import PackConfig, build_pack
from fruxel.train.sim.assetpack.licences import ALLOWED, COMMITTABLE, lookup_copyright, parse_debian_copyright
from fruxel.train.sim.assetpack.manifest import BUILDER_NAME, MANIFEST_NAME, assign_splits, builder_digest

SOURCES = Path(__file__).resolve().parents[1] / "data" / "assetpack_sources"
"""The tiny committed sources of the asset pack (scripts/make_assetpack_fixture.py; tests/conftest.py builds them)."""

SH3F = SOURCES / "debian/sweethome3d-furniture-1.8-1/usr/share/sweethome3d/furniture/BlendSwap-CC-0.sh3f"


@pytest.fixture()
def pack_copy(pack_dir: Path, tmp_path: Path) -> Path:
    dest = tmp_path / "pack"
    shutil.copytree(pack_dir, dest)
    return dest


def test_manifest_covers_every_file_with_an_allowed_licence(pack_dir: Path) -> None:
    pack = AssetPack(pack_dir)
    listed = {p for e in pack.entries for p in e.files.values()}
    on_disk = {str(p.relative_to(pack_dir)) for p in pack_dir.rglob("*") if p.is_file()} - {MANIFEST_NAME, BUILDER_NAME}
    assert on_disk == listed and len(listed) > 0
    assert {e.kind for e in pack.entries} == {"texture", "mesh", "image"}
    for e in pack.entries:
        assert e.licence in ALLOWED and e.credit and e.source.package and e.source.version and e.source.path
        # Everything the tests build from is committed, so every asset of the tiny pack must be committable.
        assert e.committable and e.licence in COMMITTABLE
        assert e.bytes == sum((pack_dir / p).stat().st_size for p in e.files.values())
    doc = json.loads((pack_dir / MANIFEST_NAME).read_text())
    assert set(doc["licences"]) == {e.licence for e in pack.entries}


def test_no_asset_is_in_both_splits(pack_dir: Path) -> None:
    pack = AssetPack(pack_dir)
    train = {e.id for e in pack.entries if e.split == "train"}
    test = {e.id for e in pack.entries if e.split == "test"}
    assert train and test and not train & test
    assert train | test == {e.id for e in pack.entries}
    for kind in ("texture", "mesh", "image"):
        for cat, n in pack.categories(kind).items():
            if n >= 2:
                assert pack.select(kind, cat, "test"), f"{kind} {cat}: no test asset"


def test_split_is_by_id_alone_about_one_fifth_and_one_test_per_category() -> None:
    groups = [(("texture", "wood"), f"src/wood-{i}") for i in range(100)] + \
             [(("mesh", "bed"), "a/bed-1"), (("mesh", "bed"), "a/bed-2"), (("mesh", "tv"), "a/tv-1")]
    s = assign_splits(groups, 0.2)
    assert sum(s[f"src/wood-{i}"] == "test" for i in range(100)) == 20
    assert sorted(s[i] for i in ("a/bed-1", "a/bed-2")) == ["test", "train"]
    assert s["a/tv-1"] == "train"
    assert assign_splits(list(reversed(groups)), 0.2) == s
    # Another asset in the group moves no id that stays clear of the boundary: the split follows the ids' hashes.
    more = assign_splits(groups + [(("texture", "wood"), "src/wood-new")], 0.2)
    assert sum(more[k] != s[k] for k in s) <= 1


def test_same_sources_give_the_same_bytes(pack_dir: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    build_pack(SOURCES, again, workers=2)
    files = sorted(p.relative_to(pack_dir) for p in pack_dir.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (pack_dir / rel).read_bytes() == (again / rel).read_bytes(), rel


def test_size_budget_is_checked_before_writing(tmp_path: Path) -> None:
    """A pack over its budget is refused before a file is written; the default budget is the 48 MiB that lets a
    pack travel to the GPU machine beside the repository."""
    assert PackConfig().max_bytes == 48 * 2**20
    out = tmp_path / "small"
    with pytest.raises(AssetPackError, match="over the .* MiB budget"):
        build_pack(SOURCES, out, PackConfig(max_bytes=20_000))
    assert not out.exists() and not list(tmp_path.iterdir())
    build_pack(SOURCES, out, PackConfig(max_bytes=2_000_000))
    with pytest.raises(AssetPackError, match="already exists"):
        build_pack(SOURCES, out)


def _rewrite_manifest(root: Path, change) -> None:
    doc = json.loads((root / MANIFEST_NAME).read_text())
    change(doc)
    (root / MANIFEST_NAME).write_text(json.dumps(doc))


def test_a_pack_names_the_code_that_built_it_and_one_built_by_other_code_is_refused(pack_copy: Path) -> None:
    """A pack built by other pack code can hold other bytes for the same sources, and so draw other rooms and test
    sets while its manifest still checks: it is refused in one line that says how to mend it, and so is a pack
    that names no builder (built before packs did)."""
    assert (pack_copy / BUILDER_NAME).read_text().strip() == builder_digest()
    assert len(AssetPack(pack_copy)) > 0
    (pack_copy / BUILDER_NAME).write_text("0123456789abcdef\n")
    with pytest.raises(AssetPackError, match=r"builder\.txt: built by pack code 0123456789abcdef, not by this "
                                             r"fruxel's \([0-9a-f]{16}\).*make assets"):
        AssetPack(pack_copy)
    (pack_copy / BUILDER_NAME).unlink()
    with pytest.raises(AssetPackError, match="built before packs named the code that built them"):
        AssetPack(pack_copy)


def test_the_builder_digest_follows_the_pack_code(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from fruxel.train.sim.assetpack import manifest

    here = Path(manifest.__file__).resolve().parent
    for name in manifest.BUILDER_MODULES:
        shutil.copy(here / f"{name}.py", tmp_path / f"{name}.py")
    monkeypatch.setattr(manifest, "__file__", str(tmp_path / "manifest.py"))
    digest = manifest.builder_digest.__wrapped__  # the computation itself, not the process's cached answer
    same = digest()
    assert same == builder_digest()
    with open(tmp_path / "meshes.py", "a") as f:
        f.write("# a change to how meshes are converted\n")
    assert digest() != same


def test_loader_refuses_a_corrupt_manifest(pack_copy: Path) -> None:
    (pack_copy / MANIFEST_NAME).write_text('{"format": "fruxel-assetpack", "version": 1, "assets": [')
    with pytest.raises(AssetPackError, match=r"manifest\.json: not a JSON manifest"):
        AssetPack(pack_copy)


@pytest.mark.parametrize("change, message", [
    (lambda d: d["assets"][0].update(licence="CC-BY-NC-4.0"), "licence 'CC-BY-NC-4.0' is not allowed"),
    (lambda d: d["assets"][0].update(split="val"), "split must be one of"),
    (lambda d: d["assets"][1].update(id=d["assets"][0]["id"]), "appears twice"),
    (lambda d: d["assets"][0]["files"].update({k: "../x.jpg" for k in d["assets"][0]["files"]}),
     "is not a plain file name"),
    (lambda d: d.update(version=2), "version 2 is not supported"),
])
def test_loader_refuses_a_malformed_entry(pack_copy: Path, change, message: str) -> None:
    _rewrite_manifest(pack_copy, change)
    with pytest.raises(AssetPackError, match=message):
        AssetPack(pack_copy)


def test_loader_refuses_a_changed_missing_or_foreign_file(pack_copy: Path) -> None:
    pack = AssetPack(pack_copy)
    mesh_file = pack_copy / pack.select("mesh")[0].files["mesh"]
    data = bytearray(mesh_file.read_bytes())
    data[len(data) // 2] ^= 0xFF
    mesh_file.write_bytes(bytes(data))
    with pytest.raises(AssetPackError, match=f"{mesh_file.name}: corrupt or changed"):
        AssetPack(pack_copy)
    # Without the hash check, decoding the file still fails in one error naming it.
    with pytest.raises(AssetPackError, match=f"{mesh_file.name}: not a valid mesh file"):
        AssetPack(pack_copy, verify=False).mesh(pack.select("mesh")[0])
    mesh_file.unlink()
    with pytest.raises(AssetPackError, match=f"{mesh_file.name}: missing"):
        AssetPack(pack_copy)


def test_loader_refuses_a_foreign_file(pack_copy: Path) -> None:
    (pack_copy / "textures" / "stray.jpg").write_bytes(b"x")
    with pytest.raises(AssetPackError, match="stray.jpg: file not listed"):
        AssetPack(pack_copy)


def test_mesh_file_with_pickle_is_refused(pack_copy: Path) -> None:
    pack = AssetPack(pack_copy)
    entry = pack.select("mesh")[0]
    path = pack_copy / entry.files["mesh"]
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    import io

    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    members["part_names.npy"] = buf.getvalue()
    with zipfile.ZipFile(path, "w") as zf:
        for n, d in members.items():
            zf.writestr(n, d)
    data = path.read_bytes()

    def relist(doc: dict) -> None:
        # A manifest that lists the pickled file faithfully: the pack opens, decoding the mesh refuses it.
        a = next(a for a in doc["assets"] if a["id"] == entry.id)
        a.update(bytes=len(data), sha256={"mesh": hashlib.sha256(data).hexdigest()})

    _rewrite_manifest(pack_copy, relist)
    with pytest.raises(AssetPackError, match="object array"):
        AssetPack(pack_copy).mesh(entry.id)


def test_records_have_their_documented_shapes_and_frames(pack_dir: Path) -> None:
    pack = AssetPack(pack_dir)
    for t in pack.textures():
        h, w = t.albedo.shape[:2]
        assert t.albedo.dtype == np.uint8 and t.albedo.shape == (h, w, 3) and max(h, w) <= 256
        assert t.normal.dtype == np.float32 and t.normal.shape == (h, w, 3)
        assert np.allclose(np.linalg.norm(t.normal, axis=-1), 1, atol=1e-3) and (t.normal[..., 2] > 0).all()
        assert t.size_m.shape == (2,) and (t.size_m > 0).all()
        assert abs(t.size_m[1] / t.size_m[0] - h / w) < 1e-6
    meshes = pack.meshes()
    assert {m.entry.category for m in meshes} == {"chair", "shelf", "lamp", "clutter"}
    for m in meshes:
        assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32 and m.face_parts.dtype == np.int32
        assert m.part_colors.shape == (len(m.part_names), 4) and m.face_parts.max() < len(m.part_names)
        lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
        assert abs(lo[2]) < 1e-6 and np.allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-5)
        assert np.allclose(hi - lo, m.size_m, atol=1e-5)
        assert m.entry.label in ("furniture", "object")
    assert len(pack.meshes(category="chair", split="train")) + len(pack.meshes(category="chair", split="test")) == 1
    for im in pack.images():
        assert im.pixels.dtype == np.uint8 and im.pixels.ndim == 3 and im.pixels.shape[2] == 3
    assert [i.entry.category for i in pack.images(category="outdoor")] == ["outdoor"]
    with pytest.raises(AssetPackError, match="unknown split"):
        pack.textures(split="val")


def _catalog_item(index: int):
    from fruxel.train.sim.assets import read_sh3f_catalog

    with zipfile.ZipFile(SH3F) as zf:
        return next(i for i in read_sh3f_catalog(zf, str(SH3F)) if i.index == index)


def test_sh3d_model_rotation_gives_an_undistorted_upright_model() -> None:
    """The phone's catalog entry rotates the model (modelRotation): applied, its own proportions match the
    catalog's size (one uniform scale); ignored, they would not, and it would be squashed."""
    from fruxel.train.sim.assetpack.meshes import read_obj, zip_resolver

    item = _catalog_item(70)
    assert item.rotation is not None and not np.allclose(item.rotation, np.eye(3))
    with zipfile.ZipFile(SH3F) as zf:
        raw = read_obj(zf.read(item.member), zip_resolver(zf, item.member.rsplit("/", 1)[0]), item.member)

    def scales(v: np.ndarray) -> np.ndarray:
        return item.size_cm / np.ptp(v, axis=0)

    rotated = scales(raw.vertices @ item.rotation.T)
    assert np.ptp(rotated) / rotated.mean() < 0.05
    unrotated = scales(raw.vertices)
    assert np.ptp(unrotated) / unrotated.mean() > 0.5


def test_sh3d_chair_stands_upright_facing_minus_y(pack_dir: Path) -> None:
    pack = AssetPack(pack_dir)
    chair = pack.meshes(category="chair")[0]
    item = _catalog_item(79)
    assert np.allclose(chair.size_m, np.array([item.size_cm[0], item.size_cm[2], item.size_cm[1]]) / 100, rtol=0.01)
    v = chair.vertices
    top = v[v[:, 2] > 0.75 * v[:, 2].max()]
    # The backrest (top quarter) is at the back: +y, the side that goes against a wall; the front faces -y.
    assert top[:, 1].mean() > 0.15 * np.ptp(v[:, 1])


def test_debian_copyright_lookup() -> None:
    text = (SOURCES / "debian/sweethome3d-furniture-1.8-1/usr/share/doc/sweethome3d-furniture/copyright").read_text()
    paras = parse_debian_copyright(text)
    assert lookup_copyright(paras, "BlendSwap-CC-0/chair.obj").licence == "CC0"
    assert lookup_copyright(paras, "KatorLegaz/x.obj").licence == "CC-BY-3.0-USA"
    assert lookup_copyright(paras, "debian/rules").licence == "CC-BY-3.0"
    with pytest.raises(KeyError):
        lookup_copyright(paras, "Other/x")


def test_cli_builds_offline_and_reports_errors_in_one_line(tmp_path: Path) -> None:
    out = tmp_path / "pack"
    cmd = [sys.executable, "-m", "fruxel.cli.sim", "assets", "--sources", str(SOURCES), "--out", str(out),
           "--offline"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    # The tiny tree lacks most packages: offline, that is one error line naming the missing one.
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "is not in the cache" in r.stderr
    assert not out.exists()
    r = subprocess.run([*cmd[:-1], "--test-fraction", "1.5"], capture_output=True, text=True)
    assert r.returncode == 2 and "--test-fraction" in r.stderr
