"""Meshes: primitives, validation, file loading, regularizers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from rsmooth import render


def test_primitives_have_the_documented_sizes():
    assert render.icosphere(3).faces.shape == (1280, 3)
    assert render.cube().faces.shape == (12, 3)
    assert render.torus(major_sections=8, minor_sections=4).faces.shape == (64, 3)
    assert render.cylinder(sections=8).faces.shape[1] == 3
    sphere = render.icosphere(2, radius=2.0)
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices, axis=1), 2.0, rtol=1e-6)


TRIANGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "empty mesh"),
        (TRIANGLE, np.array([[0, 1, 3]]), "out of range"),
        (TRIANGLE, np.array([[0, 1, -1]]), "out of range"),
        (TRIANGLE, np.array([[0, 1, 1]]), "degenerate"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]), "degenerate"),
        (np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]), "finite"),
        (TRIANGLE[:, :2], np.array([[0, 1, 2]]), r"\(V, 3\)"),
        (TRIANGLE, np.array([[0.0, 1.0, 2.0]]), "integer"),
    ],
)
def test_bad_meshes_are_rejected_with_a_clear_message(vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        render.Mesh(vertices, faces)


def test_colors_must_match_vertices():
    with pytest.raises(ValueError, match="colors"):
        render.Mesh(TRIANGLE, np.array([[0, 1, 2]]), colors=np.zeros((2, 3)))


@pytest.mark.parametrize("suffix", ["obj", "stl", "ply", "dae"])
def test_load_mesh_round_trip(tmp_path, suffix):
    if suffix == "dae":
        import collada  # noqa: F401  (installed by the [render] extra; DAE needs it)
    tm = trimesh.creation.icosphere(subdivisions=1)
    path = tmp_path / f"sphere.{suffix}"
    tm.export(path)
    mesh = render.load_mesh(path)
    assert mesh.faces.shape == (80, 3)
    np.testing.assert_allclose(sorted(np.asarray(mesh.vertices)[:, 2]), sorted(tm.vertices[:, 2]), atol=1e-5)
    normalized = render.load_mesh(path, normalize=True)
    assert float(jnp.max(jnp.linalg.norm(normalized.vertices, axis=1))) == pytest.approx(1.0)


def test_load_mesh_errors_name_the_path(tmp_path):
    missing = tmp_path / "missing.obj"
    with pytest.raises(ValueError, match="missing.obj"):
        render.load_mesh(missing)
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 this is not a mesh")
    with pytest.raises(ValueError, match="garbage.stl"):
        render.load_mesh(garbage)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(ValueError, match="empty.obj"):
        render.load_mesh(empty)


LATIN1_OBJ = b"# mod\xe8le de test (Latin-1)\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


@pytest.mark.parametrize("charset_normalizer", ["installed", "missing"])
def test_load_mesh_reads_text_that_is_not_utf8(tmp_path, monkeypatch, charset_normalizer):
    if charset_normalizer == "missing":  # trimesh's encoding guess: the loader must not need it
        monkeypatch.setitem(__import__("sys").modules, "charset_normalizer", None)
    path = tmp_path / "latin1.obj"
    path.write_bytes(LATIN1_OBJ)
    mesh = render.load_mesh(path)
    assert mesh.faces.shape == (1, 3) and mesh.vertices.shape == (3, 3)
    utf16 = tmp_path / "utf16.obj"
    utf16.write_bytes(LATIN1_OBJ.decode("latin-1").encode("utf-16"))
    assert render.load_mesh(utf16).faces.shape == (1, 3)


def test_load_mesh_says_it_cannot_parse_a_garbage_file(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "charset_normalizer", None)
    garbage = bytes(range(256)) * 4
    for suffix in ("obj", "off", "stl"):
        path = tmp_path / f"garbage.{suffix}"
        path.write_bytes(garbage)
        with pytest.raises(ValueError, match=rf"^cannot parse mesh file .*garbage\.{suffix}") as error:
            render.load_mesh(path)
        assert "charset" not in str(error.value) and "No module" not in str(error.value)


def test_regularizers():
    # A flat grid: no bending, so the normal-consistency term is zero; bending it makes it positive.
    tm = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    sphere = render.icosphere(1)
    faces = np.asarray(sphere.faces)
    v = sphere.vertices
    assert float(render.normal_consistency_loss(v, faces)) > 0
    assert float(render.normal_consistency_loss(2.0 * v, faces)) == pytest.approx(float(render.normal_consistency_loss(v, faces)))
    # Laplacian and edge terms scale as length squared.
    assert float(render.laplacian_loss(2.0 * v, faces)) == pytest.approx(4 * float(render.laplacian_loss(v, faces)))
    edges = tm.edges_unique_length
    assert float(render.edge_length_loss(tm.vertices, tm.faces)) == pytest.approx(float(np.mean(edges**2)))
    # Two coplanar triangles sharing an edge: no flattening penalty.
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert float(render.normal_consistency_loss(square, np.array([[0, 1, 2], [0, 2, 3]]))) == pytest.approx(0.0, abs=1e-12)
    grads = jax.jit(jax.grad(lambda x: render.laplacian_loss(x, faces) + render.normal_consistency_loss(x, faces) + render.edge_length_loss(x, faces)))(v)
    assert bool(jnp.all(jnp.isfinite(grads)))
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda x, f: render.laplacian_loss(x, f))(v, sphere.faces)
