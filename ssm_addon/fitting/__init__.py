"""Using a model: fitting it to new data (pose, coefficients, uncertainty) and ``ssm fit``'s targets and files.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "batch": ("FitTarget", "fit_batch", "fit_structures_to_folder", "fit_to_folder", "load_target"),
    "fit": ("FitResult", "ModelErrorField", "Pose", "Target", "correlation_length", "farthest_point_indices", "fit_any_pose", "fit_floor", "fit_model", "loo_residuals", "model_error_field", "model_error_variance", "outlier_limit", "pose_freedom", "rigid_screen", "start_poses", "weighted_pose", "axis_rotation"),
    "verdict": ("FREE_SLIDE_MM", "FREE_TURN_DEG", "UNIT_RATIO", "FitVerdict", "calibration", "coverage", "coverage_radius_mm", "is_outlier", "judge_fit", "size_in_unit_range"),
})
