"""The statistical shape model (paper 5): PCA, its files, its metrics and the quality gates.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "figures": ("FIGURE_COLOURS", "FIGURE_VIEWS", "fit_figure", "label_modes_figure", "mode_shapes", "modes_figure_cell", "optimisation_figure", "p_value_text", "principal_views", "rasterize_meshes", "render_modes_figure"),
    "files": ("NPZ_KEYS", "load_model", "load_npz", "load_statismo", "model_file", "model_from_arrays", "save_npz", "save_statismo", "write_exchange_meshes", "write_model_files", "write_npz", "write_score_tables"),
    "joint": ("INPUT_OVERLAP_MM", "INPUT_OVERLAP_SHARE", "MIN_PART_POINTS", "collision_findings", "collisions", "joined_parts", "relative_pose", "relative_poses", "shape_and_pose", "structure_model"),
    "metrics": ("AXIS_LETTERS", "AXIS_NAMES", "ModelMetrics", "aggregate_fit", "axis_letters", "compactness", "display_axes", "draw_cumulative", "draw_spectrum", "evaluate", "generalization", "import_plotting_in_background", "label_grid_picture", "metric_bars", "model_summary", "modes_figure_labels", "patient_oriented", "plot_cumulative_variance", "plot_metrics", "plot_model_figure", "plot_spectrum", "scale_bar_mm", "specificity", "view_names", "view_orientation", "write_plots"),
    "pca": ("EMPTY_MODE_SHARE", "RANDOMIZED_MIN_ELEMENTS", "ShapeModel", "drop_empty_modes", "build_model", "generalized_procrustes", "gram_factor", "leading_modes", "own_side_instances", "procrustes_fit"),
    "quality": ("Finding", "QualityError", "check_coating", "check_correspondence_rounds", "check_duplicate_instances", "check_frames", "check_input_surface", "check_landmark_transfer", "check_landmarks_on_surface", "check_model", "check_volume", "check_volumes_together", "content_digest", "loo_outlier_scores", "warnings_text"),
})
