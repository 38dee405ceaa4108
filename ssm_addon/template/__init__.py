"""The template (paper 3): surface voxels, normals and curvature; point reduction and triangulation.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "surface": ("Curvature", "DEFAULT_NORMAL_RADIUS_VOX", "DEFAULT_PATCH_RADIUS_VOX", "SurfaceGeometry", "ball_sums", "surface_curvature", "surface_geometry", "surface_graph", "surface_normals", "surface_points", "surface_voxels"),
    "template": ("Template", "TemplateParams", "Triangulation", "build_template", "clean_topology", "denser_radii", "geodesic_voronoi", "load_template", "mesh_graph", "object_volume_at_spacing", "reduce_points", "reduction_radii", "save_template", "tolerance_radii", "triangle_deviation_vox", "triangulate"),
})
