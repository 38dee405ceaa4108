"""Instances (paper 2): label maps and meshes as binary objects, the object frame, isotropic resampling.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "frame": ("SKEW_TIE", "frame_axes_moments", "frame_axes_patient", "mesh_solid_frame", "object_frame"),
    "importing": ("InstanceSpec", "file_names", "import_instance", "instance_frame", "landmark_space", "load_object", "mesh_coordinates", "mesh_frame", "mesh_instance", "object_from_mesh", "object_from_volume", "read_instance", "safe_file_name"),
    "resampling": ("resample",),
    "volume": ("ObjectFrame", "ObjectVolume", "bounding_box", "display_surface", "frame_from_arrays", "frame_to_arrays", "mirror_axis", "mirrored", "mirrored_frame", "summary"),
    "voxelize": ("THIN_PART_FAR_VOX", "keep_thin_parts", "load_mesh_volume", "mesh_edge_defects", "voxelize_mesh"),
})
