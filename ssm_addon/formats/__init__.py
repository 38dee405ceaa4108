"""File formats: their registry (extensions, kinds, coordinates), label maps, meshes, landmark files, glTF and VTK polydata.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "label_maps": ("IMAGE_EXTENSIONS", "LabelMap", "NIFTI_FORM_TOLERANCE_MM", "Volume", "label_map_coordinates", "nifti_affine", "MAX_DISTINCT_LABELS", "SUPPORTED_EXTENSIONS", "file_extension", "file_stem", "is_mesh_file", "label_counts", "load_volume", "read_label_map", "select_label", "write_label_map"),
    "landmarks": ("LANDMARK_PRESETS", "LandmarkSet", "landmark_format", "match_landmarks", "order_by_schema", "read_landmarks", "write_landmarks"),
    "meshes": ("MESH_EXTENSIONS", "SPACES", "mesh_space", "read_mesh", "read_ply", "to_ras", "write_ply"),
    "grid": ("AffineGrid",),
    "gltf": ("MM_TO_M", "Z_UP_TO_Y_UP", "read_glb", "read_glb_mesh", "write_glb"),
    "vtk": ("write_vtk", "write_vtp"),
    "registry": ("FORMATS", "KINDS", "FileFormat", "extensions", "file_glob", "format_names", "format_of", "registered_extension"),
})
