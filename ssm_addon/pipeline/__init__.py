"""The orchestrator: the study, its stage functions, the cache and the build's records.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "project_build": ("BuildResult", "build", "build_joint", "open_cache", "write_analysis_files"),
    "outputs": ("MANIFEST", "absolute_files", "check_output_folder", "check_writable", "drawing_copy", "owned_output_folder", "peak_memory_mb", "relative_files", "save_joint_outputs", "save_study_outputs", "start_drawings", "study_inputs", "write_joint", "write_outputs", "write_study"),
    "report": ("MAX_THUMBNAILS", "SECTIONS", "Absent", "Report", "instance_thumbnails", "joint_report", "model_alignment", "model_report", "study_report", "thumbnail_names", "write_html_report", "write_report_html"),
    "project": ("STRUCTURE_KEYS", "Project", "Structure", "project_text", "read_project", "structure_overrides", "targets_from_project", "toml_value", "write_project"),
    "store": ("RECORD_FIELDS", "apply_joint_records", "apply_records", "joint_records", "load_joint_study", "load_study", "load_study_or_joint", "save_joint_study", "save_study", "study_records"),
    "cache": ("BuildCache", "InstanceProduct", "code_digest", "digest", "file_digest"),
    "joint": ("JointStudy", "joint_model", "joint_sides", "run_joint", "structure_metrics"),
    "model_method": ("MEDOID_TIE", "NO_LANDMARK_TIE", "POINT_COUNT_TOLERANCE", "coat_without_landmarks_stage", "confirmed_landmark_medoid", "distance_maps_ahead", "distance_maps_kept", "keep_distance_map", "landmarked", "landmark_medoid", "landmark_medoid_template", "medoid_template", "medoid_without_landmarks", "population", "population_medoid", "refine_correspondence", "start_coatings", "template_of_count"),
    "runner": ("coating_stage", "run"),
    "sides": ("decide_sides", "given_sides", "landmark_sides", "model_side", "sides_first", "sides_line", "with_sides", "with_sides_product"),
    "optimisation": ("hold_weight", "optimisation_result", "optimisation_stage"),
    "appearance": ("appearance_stage", "learned_appearance"),
    "stages": ("coat_from_frames", "coat_instances", "coating_result", "cut_off_places", "evaluate_model", "import_instances", "import_result", "import_stage", "label_map_once", "make_model", "make_template", "metrics_stage", "model_stage", "self_check", "template_stage"),
    "streaming": ("InstanceJob", "coat_from_source", "stream_instances", "template_key"),
    "template_refinement": ("CUT_OFF_SHARE", "cut_off_instances", "with_template_refined"),
    "study": ("STAGES", "input_coordinates", "StageResult", "Study", "apply_stage", "carried_landmarks", "common_landmark_names", "instance_sources", "landmark_distances", "merge_findings", "study_parameters", "template_landmark_locations"),
})
