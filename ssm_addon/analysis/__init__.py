"""Shape analysis: what differs between groups, where on the surface, and how shape follows covariates.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "attributes": ("MISSING_TOKENS", "NAME_COLUMNS", "Attributes", "attributes_from_tables", "read_attributes",
                   "write_attributes"),
    "statistics": ("TermTest", "benjamini_hochberg", "centroid_size", "orthonormal_basis", "permutation_orders",
                   "term_test"),
    "files": ("FDR_LEVEL", "SHAPE_KEY_PREFIXES", "analysis_arrays", "analysis_document", "analysis_map_picture",
              "analysis_shape_keys", "analysis_summary", "diverging_colours", "run_analysis", "scores_picture",
              "write_analysis"),
    "shape_analysis": ("CENTROID_SIZE", "MIN_GROUP_SIZE", "Analysis", "Effect", "analyze", "design_matrix"),
})
