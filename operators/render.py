"""Pictures of a shape model: mean and ±2σ of the first modes in three views (paper fig. 10).

:func:`render_modes_figure` lays out one copy of each shape per view in a grid inside a
temporary scene (columns: axial, sagittal, coronal; rows: the mean (grey), then one row
per mode with the shapes b_k = -2√λ_k (blue) and +2√λ_k (red) of eq. (7) overlaid, as
in the paper's fig. 10: opaque, so each colour shows where its shape reaches further),
renders it once with an orthographic camera (Workbench, studio light, object outlines)
and removes the temporary scene again. Works headless with the ``bpy`` module.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import bpy
import numpy as np

from ssm_addon.model.figures import FIGURE_COLOURS, FIGURE_VIEWS, label_modes_figure, mode_shapes, modes_figure_cell
from ssm_addon.model.metrics import display_axes

from . import bridge

VIEWS = FIGURE_VIEWS  # camera looks down -Z: screen x right, screen y up (the core's figure uses the same)
COLOURS = FIGURE_COLOURS


def render_modes_figure(
    model,
    path,
    n_modes: int = 2,
    sigmas: float = 2.0,
    cell_px: int = 320,
    views=("axial", "sagittal", "coronal"),
) -> str:
    """Render the mean and ±``sigmas``·√λ of the first modes in three views into one PNG.

    Parameters
    ----------
    model : ShapeModel
        ``mean`` (N, 3) and ``modes`` (K, N, 3) in the model frame (mm), ``faces``,
        ``variances`` (K,) in mm².
    path : str or Path
        Output PNG.
    n_modes : int
        Rows of modes below the mean row (paper fig. 10: 2).
    sigmas : float
        Weight in standard deviations: b_k = ±sigmas √λ_k (paper: 2).
    cell_px : int
        Pixels per view cell; the rendered grid is ``len(views)·cell_px`` ×
        ``rows·cell_px``, and the picture adds the row labels (mean; mode k with ±σ and
        its share of the variance) and column labels (the views).

    Returns
    -------
    str
        The PNG written.
    """
    rows = mode_shapes(model, n_modes, sigmas)
    faces = np.asarray(model.faces)
    centre, cell = modes_figure_cell(model, rows)
    n_rows, n_cols = len(rows), len(views)

    scene = bpy.data.scenes.new("SSM Modes Figure")
    made_objects, made_meshes = [], []
    try:
        shown = display_axes(model)  # as the instances lay in their files (identity for patient axes)
        for r, (_, shapes) in enumerate(rows):
            for c, view in enumerate(views):
                rot = VIEWS[view] @ shown
                loc = np.array([(c - (n_cols - 1) / 2) * cell, ((n_rows - 1) / 2 - r) * cell, 0.0])
                for kind, pts in shapes:
                    name = f"SSM fig {r}-{view}-{kind}"
                    mesh = bridge.mesh_from_arrays(name, (pts - centre) @ rot.T + loc, faces)
                    obj = bpy.data.objects.new(name, mesh)
                    obj.color = COLOURS[kind]
                    scene.collection.objects.link(obj)
                    made_objects.append(obj)
                    made_meshes.append(mesh)
        cam_data = bpy.data.cameras.new("SSM fig camera")
        cam_data.type = "ORTHO"
        cam_data.ortho_scale = cell * max(n_cols, n_rows)
        cam_data.clip_end = 10.0 * cell + 1000.0
        cam = bpy.data.objects.new("SSM fig camera", cam_data)
        cam.location = (0.0, 0.0, 4.0 * cell)
        scene.collection.objects.link(cam)
        scene.camera = cam
        made_objects.append(cam)

        world = bpy.data.worlds.new("SSM fig world")
        world.color = (1.0, 1.0, 1.0)
        scene.world = world
        rd = scene.render
        rd.resolution_x, rd.resolution_y = n_cols * int(cell_px), n_rows * int(cell_px)
        rd.resolution_percentage = 100
        rd.image_settings.file_format = "PNG"
        rd.image_settings.color_mode = "RGB"
        raw = Path(tempfile.mkdtemp(prefix="ssm-fig10-")) / "grid.png"
        rd.filepath = str(raw)
        scene.view_settings.view_transform = "Standard"
        rd.engine = "BLENDER_WORKBENCH"
        shading = scene.display.shading
        shading.light = "STUDIO"
        shading.color_type = "OBJECT"
        shading.show_xray = False
        shading.show_object_outline = True
        scene.display.render_aa = "FXAA"
        bpy.ops.render.render(write_still=True, scene=scene.name)
    finally:
        for obj in made_objects:
            data = obj.data
            bpy.data.objects.remove(obj, do_unlink=True)
            if data is not None and data.users == 0:
                for coll in (bpy.data.meshes, bpy.data.cameras):
                    if data.name in coll and coll[data.name] == data:
                        coll.remove(data)
                        break
        world = scene.world
        bpy.data.scenes.remove(scene)
        if world is not None and world.users == 0:
            bpy.data.worlds.remove(world)
    try:
        import matplotlib.image as mpimg

        grid = mpimg.imread(str(raw))
        label_modes_figure(grid, path, model, n_modes=n_modes, sigmas=sigmas, views=views,
                           mm_per_px=cell / float(cell_px))
    finally:
        shutil.rmtree(raw.parent, ignore_errors=True)
    return str(path)
