"""The command line (``ssm``): its commands, the demo, the Blender step of a headless build.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "blender_layer": ("PACKAGE_NAME", "blend_writer", "blend_writer_in_child", "bpy_available", "extension_package", "extension_root"),
    "command": ("EXIT_CANCELLED", "EXIT_INPUT", "EXIT_QUALITY", "Interrupted", "argument_parser", "cmd_build", "cmd_demo", "cmd_fit", "cmd_info", "cmd_template", "main", "run", "with_overrides"),
    "demo": ("BODY_GAP", "LANDMARK_FORMATS", "MODES", "NEIGHBOUR_LABEL", "RING_RADIUS", "RING_TUBE", "SIZE", "SMOOTH_MM", "SPINOUS_RADIUS", "ShapeParams", "TRANSVERSE_RADIUS", "VERTEBRA_LABEL", "canonical_box", "landmarks_canonical", "make_demo_population", "neighbour_sdf", "pose_matrix", "rasterize", "vertebra_sdf"),
})
