"""SSM Builder core: statistical shape models from segmented volumes, without Blender.

The subpackages follow the method (Lorenz & Krahnstöver):

==================  =================================================================
``base``            the foundation: errors, parameters, progress, records, executors
``formats``         files: label maps, meshes, landmark files, glTF, VTK
``instances``       label maps and meshes as binary objects, object frame, resampling (2)
``template``        surface voxels, curvature, point reduction, triangulation (3)
``coating``         landmark warp, distance map, registration, relaxation (4)
``model``           PCA, model files, metrics, quality gates (5)
``fitting``         fitting a model to new data, the fit's verdicts, ``ssm fit``
``segmentation``    segmenting images with a model: boundary appearance, the search, ``ssm segment``
``correspondence``  the model method's rounds, the self-check, landmark proposals (3.3, 7)
``analysis``        groups and covariates
``pipeline``        the orchestrator: the study, its stages, cache, project file, outputs, report
``cli``             ``ssm …``: the build of a project, the demo
==================  =================================================================

The names a notebook needs are re-exported here (imported on first use):

>>> import ssm_addon
>>> ssm_addon.Study.__name__, ssm_addon.InputError.__module__
('Study', 'ssm_addon.base.errors')
"""

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

from ._lazy import lazy_exports
from .version import __version__ as __version__

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "pipeline.study": ("Study",),
    "pipeline.runner": ("run",),
    "base.errors": ("Cancelled", "InputError", "SSMError"),
    "base.params": ("StudyParams",),
    "pipeline.project": ("Project", "read_project", "write_project"),
    "formats.landmarks": ("LandmarkSet", "read_landmarks", "write_landmarks"),
    "pipeline.project_build": ("BuildResult", "build"),
    "instances.importing": ("InstanceSpec", "import_instance"),
    "template.template": ("Template", "build_template"),
    "coating.coating": ("CoatingResult", "coat"),
    "model.pca": ("ShapeModel", "build_model"),
    "model.files": ("load_model", "load_npz", "save_npz"),
    "fitting.fit": ("fit_model",),
    "segmentation.segment": ("segment_image",),
    "segmentation.image": ("read_image",),
})

#: Module paths of the flat layout (before the stage subpackages) -> where they live now.
#: Kept for one release so scripts written against the old paths keep working.
MOVED_MODULES = {
    "apply": "fitting.batch", "blender_layer": "cli.blender_layer", "cache": "pipeline.cache",
    "compute": "base.compute", "demo": "cli.demo",
    "distance_map": "coating.distance_map", "errors": "base.errors", "frame": "instances.frame",
    "imageio": "formats.label_maps", "landmarks": "formats.landmarks", "metrics": "model.metrics",
    "params": "base.params", "progress": "base.progress", "project": "pipeline.project_build",
    "proposal": "correspondence.proposal", "quality": "model.quality", "registration": "coating.registration",
    "relaxation": "coating.relaxation", "report": "pipeline.report", "resample": "instances.resampling",
    "resources": "base.resources", "store": "pipeline.store", "study": "pipeline.study",
    "surface": "template.surface", "volume": "instances.volume", "voxelize": "instances.voxelize",
    "warp": "coating.warp",
    # the foundation left the orchestrator's package (one build for both front ends)
    "pipeline.compute": "base.compute", "pipeline.errors": "base.errors", "pipeline.params": "base.params",
    "pipeline.progress": "base.progress", "pipeline.records": "base.records", "pipeline.resources": "base.resources",
    "formats.project_file": "pipeline.project", "formats.blender_store": "pipeline.store",
    "fitting.correspondence": "correspondence.rounds", "coating.proposal": "correspondence.proposal",
    "cli.report": "pipeline.report", "cli.project_build": "pipeline.project_build",
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """``import ssm_addon.study`` gives ``ssm_addon.pipeline.study`` (with a DeprecationWarning)."""

    def find_spec(self, fullname, path=None, target=None):
        head, _, tail = fullname.partition(".")
        if head == __name__ and tail in MOVED_MODULES:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        new = f"{__name__}.{MOVED_MODULES[spec.name.partition('.')[2]]}"
        warnings.warn(f"{spec.name} moved to {new}", DeprecationWarning, stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module):
        pass


if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
    sys.meta_path.append(_MovedModuleFinder())
