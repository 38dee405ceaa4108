"""The study and its stages, the parameters, the executors and cache, progress and errors.

Every public name of the subpackage's modules, imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "cache": ("BuildCache", "InstanceProduct", "digest", "file_digest"),
    "compute": ("CONNECT_TIMEOUT_S", "Executor", "SCHEDULERS", "check_scheduler", "dask_setup", "executor_or_local", "ignore_sigint", "probe_scheduler", "run_one_thread", "start_resource_tracker", "stop_children", "time_left_text", "usable_cores"),
    "errors": ("Cancelled", "InputError", "SSMError", "check_cancelled"),
    "params": ("AnalysisParams", "CoatingParams", "ComputeParams", "CorrespondenceParams", "FitParams", "ModelParams", "OutputParams", "QualityParams", "SECTIONS", "Spec", "StudyParams", "TABLES", "TemplateParams", "add_arguments", "check", "from_arguments", "from_table", "param", "shortest_float32", "specs", "to_table", "type_name"),
    "progress": ("report", "sub_progress"),
    "records": ("jsonable", "versions"),
    "resources": ("BYTES_PER_OBJECT_VOXEL", "check_allocation", "memory_limit_bytes"),
    "study": ("InstanceJob", "STAGES", "StageResult", "Study", "apply_stage", "carried_landmarks", "coat_from_source", "coat_instances", "coating_result", "coating_stage", "common_landmark_names", "evaluate_model", "import_instances", "import_result", "import_stage", "landmark_distances", "make_model", "make_template", "medoid_template", "merge_findings", "metrics_stage", "model_stage", "population_medoid", "refine_correspondence", "run", "start_coatings", "stream_instances", "study_parameters", "template_landmark_locations", "template_stage"),
})
