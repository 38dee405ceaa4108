"""File formats: label maps, landmark files, the project file, VTK polydata and the hand-over of a study to Blender.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "blender_store": ("load_study", "save_study"),
    "label_maps": ("IMAGE_EXTENSIONS", "LabelMap", "Volume", "MAX_DISTINCT_LABELS", "SUPPORTED_EXTENSIONS", "file_extension", "file_stem", "is_mesh_file", "label_counts", "load_volume", "read_label_map", "select_label", "write_label_map"),
    "landmarks": ("LANDMARK_PRESETS", "LandmarkSet", "landmark_format", "match_landmarks", "order_by_schema", "read_landmarks", "write_landmarks"),
    "project_file": ("Project", "project_text", "read_project", "toml_value", "write_project"),
    "meshes": ("MESH_EXTENSIONS", "read_mesh", "read_ply", "write_ply"),
    "gltf": ("MM_TO_M", "read_glb", "write_glb"),
    "vtk": ("write_vtk", "write_vtp"),
})
