"""Using a model: fitting it to new data, and the model-guided correspondence rounds.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "batch": ("FitTarget", "fit_batch", "fit_to_folder", "load_model", "load_target"),
    "correspondence": ("AXIS_TURNS", "WORLD_POSE_TOLERANCE", "CorrespondenceCheck", "LandmarkNoise", "RoundFigures", "RoundLandmarks", "aligned_to", "check_correspondence", "coat_mean_shape", "correspondence_fit_params", "landmark_noise", "landmark_transfer", "refine_instance", "refine_rounds", "resample_instance", "round_fits", "round_helps", "round_landmarks", "start_from_model", "starts_from_model"),
    "fit": ("FitResult", "ModelErrorField", "Pose", "Target", "correlation_length", "farthest_point_indices", "fit_any_pose", "fit_model", "loo_residuals", "model_error_field", "model_error_variance", "outlier_limit", "rigid_screen", "start_poses"),
})
