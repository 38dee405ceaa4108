"""Segmenting images with a model: learned boundary appearance, the active shape model search, the files.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "appearance": ("Appearance", "LEVEL_SIGMAS_MM", "appearance_from_arrays", "boundary_grey_values", "learn_appearance", "load_appearance", "normalised_derivative", "profile_features", "read_own_appearance_h5", "read_scalismo_asm", "write_appearance_h5", "write_scalismo_asm"),
    "files": ("FIGURE_MARGIN_MM", "SCALE_BAR_MM", "SEGMENT_FILES", "VIEWS", "SegmentationRecord", "parse_point", "segment_figure", "segment_files", "structure_labels", "truth_scores", "view_plane", "write_segmentation"),
    "image": ("PLANES", "GreyImage", "read_image", "segmentation_mask", "window_values", "world_slice"),
    "scores": ("degrade_image", "mask_surface_points", "segmentation_scores"),
    "segment": ("BONE_HU", "BONE_REACH_MM", "CT_AIR_HU", "MIN_SCANS", "SegmentResult", "bone_near", "landmark_pose", "segment_image", "start_pose", "typical_rotation", "volume_centroid"),
})
