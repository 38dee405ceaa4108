"""The orchestrator: the study, its stage functions, the cache and the build's records.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "project": ("Project", "project_text", "read_project", "targets_from_project", "toml_value", "write_project"),
    "store": ("load_study", "save_study"),
    "cache": ("BuildCache", "InstanceProduct", "digest", "file_digest"),
    "study": ("InstanceJob", "STAGES", "StageResult", "Study", "apply_stage", "carried_landmarks", "coat_from_source", "coat_instances", "coating_result", "coating_stage", "common_landmark_names", "evaluate_model", "import_instances", "import_result", "import_stage", "landmark_distances", "make_model", "make_template", "medoid_template", "merge_findings", "metrics_stage", "model_stage", "population_medoid", "refine_correspondence", "run", "start_coatings", "stream_instances", "study_parameters", "template_landmark_locations", "template_stage"),
})
