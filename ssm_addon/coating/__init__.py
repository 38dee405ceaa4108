"""Coating (paper 4): landmark warp, distance map, surface registration, mass-spring relaxation.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "coating": ("CoatingCancelled", "CoatingParams", "CoatingStart", "CoatingResult", "FitFigures", "coat", "coat_all", "coat_from_start", "template_mesh"),
    "distance_map": ("DistanceMap", "gradient_into"),
    "registration": ("reach_far_parts", "register_to_surface"),
    "relaxation": ("folded_triangles", "relax", "untangle"),
    "warp": ("KERNELS", "ThinPlateSpline", "fold_free_warp", "landmark_warp", "warp_jacobian_det"),
})
