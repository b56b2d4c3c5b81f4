"""Reading users' mesh files with their materials (omniscs.agents.meshfile) and importing them into the pool."""
import numpy as np
import pytest
import trimesh
from PIL import Image
from trimesh.visual import TextureVisuals
from trimesh.visual.material import PBRMaterial, SimpleMaterial

from omniscs.agents.meshfile import (DIELECTRIC_F0, MAX_SHININESS, MIN_SHININESS, pbr_to_phong, read_mesh_file,
                                     roughness_to_shininess, srgb_to_linear)
from omniscs.errors import ValidationError


def _pbr(mesh, **kw):
    mesh.visual = TextureVisuals(uv=np.random.default_rng(0).random((len(mesh.vertices), 2)),
                                 material=PBRMaterial(**kw))
    return mesh


def _two_part_glb(path):
    """A red dielectric body (roughness 0.3) and a grey metal dome (roughness 0.2) placed 1 m along +x by its node."""
    body = _pbr(trimesh.creation.box((4.0, 1.8, 1.4)), baseColorFactor=[200, 30, 30, 255], metallicFactor=0.0,
                roughnessFactor=0.3)
    dome = _pbr(trimesh.creation.icosphere(2, 0.5), baseColorFactor=[180, 180, 190, 255], metallicFactor=1.0,
                roughnessFactor=0.2)
    dome.apply_translation([0.0, 0.0, 1.2])
    scene = trimesh.Scene()
    scene.add_geometry(body, node_name="body")
    scene.add_geometry(dome, node_name="dome", transform=trimesh.transformations.translation_matrix([1.0, 0, 0]))
    scene.export(path)
    return len(body.faces), len(dome.faces)


def test_gltf_metallic_roughness_becomes_albedo_specular_and_shininess(tmp_path):
    n_body, n_dome = _two_part_glb(tmp_path / "car.glb")
    m = read_mesh_file(tmp_path / "car.glb")
    assert m.materials == ("pbr", "pbr") and len(m.faces) == n_body + n_dome
    assert np.allclose(m.vertices.max(0), [2.0, 0.9, 1.7], atol=1e-5)  # the dome's node moved it to x = 1, z = 1.2
    red = srgb_to_linear(np.array([200, 30, 30]) / 255.0)
    grey = srgb_to_linear(np.array([180, 180, 190]) / 255.0)
    body = np.all(np.isclose(m.colour, red, atol=1e-6), axis=1)
    dome = np.all(np.isclose(m.colour, grey, atol=1e-6), axis=1)
    assert body.sum() == n_body and dome.sum() == n_dome
    # the dielectric keeps its colour as albedo and reflects 4 % head-on; the metal has no diffuse part and
    # reflects its mean colour
    assert np.allclose(m.albedo[body], red) and np.allclose(m.specular[body], DIELECTRIC_F0)
    assert np.allclose(m.albedo[dome], 0.0) and np.allclose(m.specular[dome], grey.mean())
    assert np.allclose(m.shininess[body], 2 / 0.3 ** 4 - 2) and np.allclose(m.shininess[dome], 2 / 0.2 ** 4 - 2)


def test_a_base_colour_texture_is_sampled_per_face(tmp_path):
    """A texture red on its left half and blue on its right: faces mapped left are red, right blue; with no
    metallic factor glTF's default (1: a metal) holds."""
    image = Image.fromarray(np.array([[[255, 0, 0], [0, 0, 255]]], np.uint8))
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    uv = np.stack([np.where(box.vertices[:, 0] > 0, 0.9, 0.1), np.full(len(box.vertices), 0.5)], 1)
    box.visual = TextureVisuals(uv=uv, material=PBRMaterial(baseColorTexture=image))
    box.export(tmp_path / "tex.glb")
    m = read_mesh_file(tmp_path / "tex.glb")
    side = box.vertices[box.faces][:, :, 0]
    right, left = (side > 0).all(1), (side < 0).all(1)
    assert right.any() and left.any()
    assert np.allclose(m.colour[right], [0, 0, 1]) and np.allclose(m.colour[left], [1, 0, 0])
    assert np.allclose(m.specular, 1 / 3) and np.allclose(m.albedo, 0.0)  # metallic 1 (the default)


@pytest.mark.parametrize("ks, f0", [([128, 128, 128, 255], DIELECTRIC_F0), ([0, 0, 0, 255], 0.0)])
def test_an_mtl_material_gives_a_glossy_dielectric_or_a_matte_surface(tmp_path, ks, f0):
    box = trimesh.creation.box((2.0, 1.0, 1.0))
    box.visual = TextureVisuals(uv=np.zeros((len(box.vertices), 2)),
                                material=SimpleMaterial(diffuse=[20, 100, 20, 255], specular=ks, glossiness=50))
    box.export(tmp_path / "van.obj")
    m = read_mesh_file(tmp_path / "van.obj")
    assert m.materials == ("mtl",)
    assert np.allclose(m.albedo, srgb_to_linear(np.array([20, 100, 20]) / 255.0), atol=1e-6)
    assert np.allclose(m.specular, f0) and np.allclose(m.shininess, 50.0)


def test_colours_only_or_nothing_is_matte(tmp_path):
    box = trimesh.creation.box((2.0, 1.0, 1.0))
    box.visual.face_colors = [10, 200, 10, 255]
    box.export(tmp_path / "c.ply")
    m = read_mesh_file(tmp_path / "c.ply")
    assert m.materials == ("colours",) and m.specular is None and m.shininess is None
    assert np.allclose(m.colour, srgb_to_linear(np.array([10, 200, 10]) / 255.0), atol=1e-6)
    trimesh.creation.box((2.0, 1.0, 1.0)).export(tmp_path / "plain.stl")
    plain = read_mesh_file(tmp_path / "plain.stl")
    assert plain.specular is None and np.allclose(plain.colour, srgb_to_linear(np.full(3, 0.6)))


def test_material_extremes_stay_finite_and_in_range():
    r = np.array([0.0, 1e-6, 0.5, 1.0, -3.0, 7.0])
    s = roughness_to_shininess(r)
    assert np.isfinite(s).all() and s.min() >= MIN_SHININESS and s.max() <= MAX_SHININESS
    assert s[0] == MAX_SHININESS and s[3] == MIN_SHININESS
    albedo, f0, shin = pbr_to_phong(np.array([[2.0, -1.0, 0.5]] * 3), np.array([-1.0, 0.5, 9.0]), r[:3])
    for a in (albedo, f0, shin):
        assert np.isfinite(a).all()
    assert albedo.min() >= 0 and albedo.max() <= 1 and f0.min() >= 0 and f0.max() <= 1


def test_unreadable_or_empty_files_are_clear_errors(tmp_path):
    (tmp_path / "empty.obj").write_text("# nothing\n")
    with pytest.raises(ValidationError, match="no triangles|not a mesh"):
        read_mesh_file(tmp_path / "empty.obj")
    (tmp_path / "junk.glb").write_bytes(b"not a gltf at all")
    with pytest.raises(ValidationError, match="not a mesh trimesh can read"):
        read_mesh_file(tmp_path / "junk.glb")


@pytest.mark.slow
def test_an_imported_gltf_keeps_its_colours_and_materials_in_the_pool(tmp_path):
    """Before the materials were read, a glTF with a PBR material came in grey and matte."""
    from omniscs.agents.pool import Pool
    from omniscs.render.sh import SH_C0, SH_COLOR_OFFSET

    _two_part_glb(tmp_path / "car.glb")
    pool = Pool(tmp_path / "pool")
    model = pool.get(pool.import_file(tmp_path / "car.glb", "car"))
    assert model.meta["build"]["materials"] == ["pbr"]
    spec = model.material.specular.numpy()
    assert np.isclose(spec, DIELECTRIC_F0).mean() > 0.5 and (spec > 0.3).any()  # body dielectric, dome metal
    colours = np.clip(SH_COLOR_OFFSET + SH_C0 * model.params.sh_dc.detach().numpy(), 0, 1)
    body = np.isclose(spec, DIELECTRIC_F0)
    assert np.median(colours[body, 0]) > 2 * np.median(colours[body, 1])  # red, not a neutral grey
