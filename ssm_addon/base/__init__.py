"""The foundation every stage stands on: errors, parameters, progress, records, resources, executors.

Imports no stage (``tests/test_structure.py`` holds it): the stages and the orchestrator
import these, never the other way round. Every public name of the subpackage's modules,
imported on first use (:mod:`ssm_addon._lazy`).
"""

from .._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "compute": ("CONNECT_TIMEOUT_S", "Executor", "SCHEDULERS", "check_scheduler", "dask_setup", "done_future", "executor_or_local", "ignore_sigint", "import_modules", "inner_threads", "probe_scheduler", "run_one_thread", "signals_deferred", "start_resource_tracker", "stop_children", "time_left_text", "usable_cores"),
    "errors": ("Cancelled", "InputError", "SSMError", "check_cancelled"),
    "params": ("ALIGNMENTS", "AnalysisParams", "CoatingParams", "ComputeParams", "CorrespondenceParams", "FRAME_METHODS", "FitParams", "JointParams", "ModelParams", "OutputParams", "QualityParams", "SECTIONS", "SegmentParams", "Spec", "StudyParams", "TABLES", "TemplateParams", "add_arguments", "check", "from_arguments", "from_table", "param", "shortest_float32", "specs", "to_table", "type_name"),
    "progress": ("report", "sub_progress"),
    "records": ("jsonable", "versions"),
    "resources": ("BYTES_PER_OBJECT_VOXEL", "check_allocation", "memory_limit_bytes"),
})
