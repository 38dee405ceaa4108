"""Correspondence beyond the paper's single pass: the model method's start and rounds, the
landmark transfer self-check, the correspondence optimised across the population, and
landmarks proposed for a new instance.

The coating stage's correspondence (paper 3.3 and 7): the per-instance steps are pure
functions of arrays and products (coatings, volumes, the template), so the rounds run in
processes. The study-level loop that chooses and applies them is the orchestrator's
(:mod:`ssm_addon.pipeline.model_method`). Every public name of the subpackage's modules,
imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "frames": ("FRAME_ROTATIONS", "ROTATION_NAMES", "nearest_frame_rotation", "TURN_NAMES", "TURNED_FACTOR", "FramesStart", "SurfacePairs", "area_samples", "input_rotation", "surface_similarity", "coat_from_template_pose", "coat_without_landmarks", "far_from_population", "population_turns", "template_start", "TWIST_FACTOR", "TWIST_MIN_DEG", "Twist", "coating_twists", "twisted"),
    "optimisation": ("EXACT_SVD_MAX_INSTANCES", "INNER_STEPS", "InstanceSource", "LandmarkHold", "Optimisation", "OptimisationCancelled", "OptimisationStep", "entropy_pull", "landmark_holds", "optimise_correspondence", "slide_on_surface"),
    "proposal": ("PROPOSAL_METHODS", "propose_by_model", "propose_from_meshes", "propose_landmarks", "propose_landmarks_by_coating", "surface_points_object", "transfer_landmarks"),
    "sides": ("SIDE_FACTOR", "SideDecision", "landmark_side", "subject_sides", "surface_side"),
    "rounds": ("SELF_CHECK_INSTANCES", "SELF_CHECK_OTHERS", "evenly_spaced", "AXIS_TURNS", "Population", "WORLD_POSE_TOLERANCE", "CorrespondenceCheck", "LandmarkNoise", "RoundFigures", "RoundLandmarks", "aligned_to", "check_correspondence", "coat_mean_shape", "correspondence_fit_params", "landmark_noise", "landmark_transfer", "refine_instance", "refine_rounds", "resample_instance", "round_fits", "round_helps", "round_landmarks", "start_from_model", "starts_from_model"),
})
