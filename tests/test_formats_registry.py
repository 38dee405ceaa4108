"""The formats registry: every registered format is read by its kind's reader, and the command
line, Blender's file filters and the messages list what the registry holds."""

from __future__ import annotations

import numpy as np
import pytest

from ssm_addon.base.errors import InputError
from ssm_addon.formats import registry
from ssm_addon.formats.label_maps import read_image_array, read_label_map, write_label_map
from ssm_addon.formats.landmarks import LandmarkSet, read_landmarks, write_landmarks
from ssm_addon.formats.meshes import read_mesh


def _tetrahedron():
    v = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


def _write_mesh(path, v, f):
    ext = registry.registered_extension(path)
    if ext == ".stl":
        lines = ["solid t"]
        for tri in f:
            lines += ["facet normal 0 0 0", "outer loop", *(f"vertex {x} {y} {z}" for x, y, z in v[tri]), "endloop",
                      "endfacet"]
        path.write_text("\n".join(lines + ["endsolid t"]) + "\n")
    elif ext == ".obj":
        path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n"
                                                                             for a, b, c in f))
    else:
        from ssm_addon.formats.meshes import write_ply

        write_ply(path, v, f)


@pytest.mark.parametrize("ext", registry.extensions("label map"))
def test_every_label_map_format_of_the_registry_reads_back(tmp_path, ext):
    labels = np.zeros((5, 6, 7), np.int16)
    labels[1:4, 2:5, 3:6] = 3
    affine = np.diag([1.5, 2.0, 2.5, 1.0])
    affine[:3, 3] = [-10.0, 5.0, 20.0]
    path = tmp_path / f"seg{ext}"
    if ext == ".npy":
        np.save(path, labels)
        got = read_label_map(path, spacing_mm=(1.5, 2.0, 2.5))
        np.testing.assert_array_equal(got.labels, labels)
        return
    write_label_map(path, labels, affine)
    got = read_label_map(path)
    np.testing.assert_array_equal(got.labels, labels)
    np.testing.assert_allclose(got.affine, affine, atol=1e-6)
    if ext in registry.extensions("image"):  # a grey-value image of the same format
        data, aff, _p = read_image_array(path)
        np.testing.assert_array_equal(data, labels)


@pytest.mark.parametrize("ext", registry.extensions("mesh"))
def test_every_mesh_format_of_the_registry_reads_back(tmp_path, ext):
    v, f = _tetrahedron()
    path = tmp_path / f"t{ext}"
    _write_mesh(path, v, f)
    got_v, got_f = read_mesh(path)
    assert len(got_f) == 4
    np.testing.assert_allclose(np.sort(got_v, axis=0), np.sort(v, axis=0))


@pytest.mark.parametrize("ext", registry.extensions("landmarks"))
def test_every_landmark_format_of_the_registry_reads_back(tmp_path, ext):
    lm = LandmarkSet(("a", "b", "c"), np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.5]]), "x")
    path = write_landmarks(tmp_path / f"lm{ext}", lm) or tmp_path / f"lm{ext}"
    got = read_landmarks(path)
    assert got.names == lm.names
    np.testing.assert_allclose(got.points_world, lm.points_world, atol=1e-6)


def test_the_messages_the_help_and_the_file_filters_list_the_registry(tmp_path):
    from ssm_addon.cli.command import argument_parser

    assert registry.format_names("mesh") == "STL/PLY/OBJ"
    assert registry.file_glob("image") == "*.nii;*.nii.gz;*.nrrd;*.nhdr;*.mha;*.mhd"
    assert registry.file_glob("model") == "*.npz;*.h5;*.hdf5"
    (tmp_path / "case.stl").mkdir()
    with pytest.raises(InputError, match=r"is a folder, not a mesh file \(STL, PLY, OBJ\)"):
        read_mesh(tmp_path / "case.stl")
    with pytest.raises(InputError, match=r"unknown file extension '\.dcm'; supported: \.stl, \.ply, \.obj"):
        read_mesh(tmp_path / "scan.dcm")
    with pytest.raises(InputError, match=r"use \.fcsv, \.mrk\.json, \.csv or \.json"):
        read_landmarks(tmp_path / "pts.txt")
    parser = argument_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    helps = {name: " ".join(a.help or "" for a in p._actions) for name, p in sub.items()}
    assert "STL/PLY/OBJ" in helps["template"] and "STL/PLY/OBJ" in helps["fit"]
    assert registry.format_names("image", ", ") in helps["segment"]
    with pytest.raises(ValueError, match="unknown kind"):
        registry.extensions("video")


@pytest.mark.blender
def test_blenders_file_filters_are_the_registrys(bpy_clean):
    from ssm.operators.instances import FILE_GLOB as instances_glob
    from ssm.operators.landmarks import FILE_GLOB as landmarks_glob

    bpy = bpy_clean
    assert instances_glob == ";".join(f"*{e}" for e in registry.extensions("label map") + registry.extensions("mesh"))
    assert landmarks_glob == registry.file_glob("landmarks")
    for op, kind in ((bpy.ops.ssm.import_model, "model"), (bpy.ops.ssm.import_image, "image"),
                     (bpy.ops.ssm.import_landmarks, "landmarks")):
        glob = op.get_rna_type().properties["filter_glob"].default
        assert glob == registry.file_glob(kind), (op, glob)
