"""The appearance stage: the boundary's look learned from the instances' images.

When project instances name a grey-value ``image`` (CT in the same world space as their label
map or mesh), the model's points on each such instance (its coating, world mm) are sampled
along their normals in its image and the profiles per point become the model's appearance
(:func:`ssm_addon.segmentation.learn_appearance`). A stage of :data:`~.study.STAGES` after the
model (it reads the model's mean and the instances' coatings); the writer stores its product in
``model.npz`` beside the shape model (``appearance_*`` arrays) and in the statismo file, for
``ssm segment``, and ``report.json``/``report.html`` record it.
"""

from __future__ import annotations

import time

from ..base.errors import InputError
from ..segmentation.appearance import learn_appearance
from ..segmentation.image import read_image
from .study import StageResult

__all__ = ["appearance_stage", "learned_appearance"]


def appearance_stage(study) -> StageResult:
    """The appearance stage: :func:`learned_appearance` of a study with its model, as a
    :class:`~.study.StageResult` (``appearance``, ``appearance_record``: None when no instance
    names an image; the summary line says what was learned).

    Raises
    ------
    InputError
        An image that cannot be read, or that does not cover its instance's surface.
    """
    t0 = time.perf_counter()
    lines: list = []
    appearance, doc = learned_appearance(study, log=lines.append)
    return StageResult("appearance", {"appearance": appearance, "appearance_record": doc}, (),
                       {"appearance": time.perf_counter() - t0} if appearance is not None else {}, tuple(lines))


def learned_appearance(study, *, log=None):
    """(Appearance or None, report entry or None) of a built study: None when no instance names an image.

    Raises
    ------
    InputError
        An image that cannot be read, or that does not cover its instance's surface (the
        message names the instance and the file).
    """
    model = study.model
    names = [str(n) for n in model.instance_names]
    rows, images = [], []
    read: dict = {}  # several instances (the vertebrae of one CT) often name one image: read it once
    for i, name in enumerate(names):
        spec = study.instance(name)
        path = getattr(spec, "image_path", None)
        if path is None:
            continue
        if path not in read:
            read[path] = read_image(path)
        img = read[path]
        inside = img.contains(model.instance_points_world[i])
        if inside.mean() < 0.95:
            raise InputError(f"instance {name!r}: its image {path} covers {100 * inside.mean():.0f} % of the "
                             "instance's surface; the image must be in the same world space as the label map or mesh "
                             "(same scanner coordinates) and hold the whole structure")
        rows.append(i)
        images.append(img)
    if not rows:
        return None, None
    t0 = time.perf_counter()
    appearance = learn_appearance(model.mean, model.faces, [model.instance_points_world[i] for i in rows], images,
                                  names=[names[i] for i in rows])
    doc = {**appearance.to_dict(), "seconds": time.perf_counter() - t0}
    if log is not None:
        log(f"appearance: boundary profiles learned from the images of {len(rows)} of {len(names)} instances "
            f"({', '.join(names[i] for i in rows[:5])}{'…' if len(rows) > 5 else ''}); inside "
            f"{appearance.boundary_mm[0]:.0f}, outside {appearance.boundary_mm[1]:.0f} (grey values)")
    return appearance, doc
