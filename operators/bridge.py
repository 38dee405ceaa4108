"""The numpy <-> bpy bridge: meshes, attributes, shape keys, collections and empties.

All geometry is float32/int32 through ``foreach_get``/``foreach_set``; no per-vertex
Python loops. Blender units are millimetres (one Blender unit = 1 mm; the scene's unit
scale is set to 0.001 m so the viewport shows mm).
"""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix, Vector

INSTANCES_COLLECTION = "SSM Instances"


def ensure_mm_units(scene: bpy.types.Scene) -> None:
    """Show lengths in mm: one Blender unit is one millimetre."""
    us = scene.unit_settings
    if us.system != "METRIC" or abs(us.scale_length - 0.001) > 1e-12:
        us.system = "METRIC"
        us.scale_length = 0.001
        us.length_unit = "MILLIMETERS"


def ensure_collection(scene: bpy.types.Scene, name: str) -> bpy.types.Collection:
    """Return the collection ``name`` linked to the scene, creating it if needed."""
    coll = bpy.data.collections.get(name)
    if coll is None:
        coll = bpy.data.collections.new(name)
    if scene.collection.children.get(coll.name) is None and coll.name not in {
        c.name for c in scene.collection.children_recursive
    }:
        scene.collection.children.link(coll)
    return coll


def mesh_from_arrays(name: str, vertices: np.ndarray, faces: np.ndarray, mesh=None) -> bpy.types.Mesh:
    """Create (or refill) a triangle mesh from (V, 3) vertices and (F, 3) faces."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    if mesh is None:
        mesh = bpy.data.meshes.new(name)
    else:
        mesh.clear_geometry()
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", vertices.ravel())
    mesh.loops.add(faces.size)
    mesh.loops.foreach_set("vertex_index", faces.ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    mesh.validate(verbose=False)
    return mesh


def mesh_vertices(mesh: bpy.types.Mesh) -> np.ndarray:
    """(V, 3) float64 vertex coordinates of ``mesh`` in its object frame."""
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def mesh_triangles(mesh: bpy.types.Mesh) -> np.ndarray:
    """(F, 3) int triangles of ``mesh`` (polygons triangulated via loop triangles)."""
    mesh.calc_loop_triangles()
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3).astype(np.int64)


def object_world_vertices(obj: bpy.types.Object) -> np.ndarray:
    """(V, 3) vertices of a mesh object in Blender world coordinates (mm)."""
    m = np.array(obj.matrix_world, dtype=float)
    v = mesh_vertices(obj.data)
    return v @ m[:3, :3].T + m[:3, 3]


def set_matrix_world(obj: bpy.types.Object, matrix: np.ndarray) -> None:
    """Set ``obj.matrix_world`` from a (4, 4) numpy array."""
    obj.matrix_world = Matrix(np.asarray(matrix, dtype=float).tolist())


def matrix_to_numpy(matrix) -> np.ndarray:
    """A mathutils Matrix as a (4, 4) float64 array."""
    return np.array([list(row) for row in matrix], dtype=float)


def store_arrays(idblock, key: str, arrays: dict) -> None:
    """Keep arrays in the ID property ``idblock[key]`` exactly (float64 / int32 buffers).

    Strings are stored as they are. Survives saving and re-opening the .blend bit for bit.
    """
    group = {}
    for name, value in arrays.items():
        if isinstance(value, str):
            group[name] = value
            continue
        a = np.asarray(value)
        group[f"{name}__shape"] = np.asarray(a.shape, dtype=np.int32) if a.ndim else np.zeros(0, np.int32)
        if np.issubdtype(a.dtype, np.integer):
            group[name] = np.ascontiguousarray(a, dtype=np.int32).ravel()
        else:
            group[name] = np.ascontiguousarray(a, dtype=np.float64).ravel()
    idblock[key] = group


def load_arrays(idblock, key: str) -> dict | None:
    """The arrays stored by :func:`store_arrays` (float64 / int64), or None."""
    group = idblock.get(key)
    if group is None:
        return None
    out = {}
    for name in group.keys():
        if name.endswith("__shape"):
            continue
        value = group[name]
        if isinstance(value, str):
            out[name] = value
            continue
        shape = tuple(int(x) for x in np.asarray(group.get(f"{name}__shape", []), dtype=np.int64))
        a = np.asarray(value)
        a = a.astype(np.int64) if np.issubdtype(a.dtype, np.integer) else a.astype(np.float64)
        out[name] = a.reshape(shape) if shape else a
    return out


#: The posterior SD colour scale (mm): blue at 0, red at this and above, the same for every fit and
#: segmentation so colours compare between objects; the legend (:func:`sd_legend`) says it.
SD_SCALE_MM = 3.0


def sd_colours(sd: np.ndarray) -> np.ndarray:
    """(N, 4) RGBA from posterior standard deviations (mm) on the fixed scale 0 .. ``SD_SCALE_MM``:
    blue (certain) to red (``SD_SCALE_MM`` or more)."""
    rel = np.clip(np.asarray(sd, float) / SD_SCALE_MM, 0.0, 1.0)
    rgba = np.ones((len(sd), 4), dtype=np.float32)
    rgba[:, 0] = 0.15 + 0.8 * rel
    rgba[:, 1] = 0.35 + 0.3 * (1 - np.abs(2 * rel - 1))
    rgba[:, 2] = 0.9 - 0.75 * rel
    return rgba


def sd_legend(context, near: np.ndarray, collection_name: str) -> bpy.types.Object:
    """The posterior SD colour scale as a bar of 30 mm with its values in mm, beside the world points
    ``near`` (10 mm beyond their largest x, at their mid height); one legend per scene, moved to the
    latest result. Returns the bar (the labels are its children)."""
    p = np.asarray(near, float).reshape(-1, 3)
    lo, hi = p.min(axis=0), p.max(axis=0)
    origin = np.array([hi[0] + 10.0, 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2]) - 15.0])
    steps = 16
    z = np.linspace(0.0, 30.0, steps + 1)
    verts = np.concatenate([np.stack([np.zeros_like(z), np.zeros_like(z), z], 1),
                            np.stack([np.full_like(z, 4.0), np.zeros_like(z), z], 1)])
    faces = np.array([t for k in range(steps) for t in ([k, steps + 1 + k, steps + 2 + k],
                                                        [k, steps + 2 + k, k + 1])])
    matrix = np.eye(4)
    matrix[:3, 3] = origin
    bar = new_mesh_object(context, "SSM SD legend", verts, faces, collection_name=collection_name, matrix_world=matrix)
    set_vertex_colors(bar.data, sd_colours(np.concatenate([z, z]) / 30.0 * SD_SCALE_MM), name="posterior_sd")
    mat = color_material("SSM Posterior SD", attribute="posterior_sd")
    if not bar.data.materials:
        bar.data.materials.append(mat)
    for k, value in enumerate((0.0, 0.5 * SD_SCALE_MM, SD_SCALE_MM)):
        name = f"SSM SD legend {k}"
        label = bpy.data.objects.get(name)
        if label is None or label.type != "FONT":
            label = bpy.data.objects.new(name, bpy.data.curves.new(name, "FONT"))
            ensure_collection(context.scene, collection_name).objects.link(label)
        label.data.body = f"{value:g} mm" if k < 2 else f"{value:g} mm or more (posterior SD)"
        label.data.size = 3.0
        label.parent = bar
        label.matrix_parent_inverse = Matrix.Identity(4)
        label.location = (6.0, 0.0, 15.0 * k - 1.0)
        label.rotation_euler = (np.pi / 2, 0.0, 0.0)  # read from the front (looking along +y)
    return bar


def position_colors(points: np.ndarray) -> np.ndarray:
    """(N, 4) RGBA: a smooth colour by position (each axis of the points' box -> R, G, B).

    Computed from the template's points and given to every mesh that shares the
    template's vertices (template, coated instances, model), corresponding places have
    the same colour everywhere: correspondence visible at a glance.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    rgba = np.ones((len(p), 4), dtype=np.float32)
    if len(p):
        lo, hi = p.min(axis=0), p.max(axis=0)
        rgba[:, :3] = 0.12 + 0.83 * (p - lo) / np.where(hi > lo, hi - lo, 1.0)
    return rgba


def triangle_index_colors(n_faces: int) -> np.ndarray:
    """(F, 4) float32 RGBA: a distinct colour per triangle index (golden-ratio hues).

    Triangle i has the same colour on the template, every coated instance and the
    model, which shows correspondence the way the paper's figs. 6-7 do.
    """
    i = np.arange(n_faces)
    hue = (i * 0.6180339887498949) % 1.0
    sat = 0.55 + 0.35 * ((i * 7) % 5) / 4.0
    val = 0.65 + 0.35 * ((i * 3) % 4) / 3.0
    # HSV -> RGB, vectorised (colorsys.hsv_to_rgb per element)
    sector = np.floor(hue * 6.0).astype(int) % 6
    f = hue * 6.0 - np.floor(hue * 6.0)
    p, q, t = val * (1 - sat), val * (1 - sat * f), val * (1 - sat * (1 - f))
    table = np.stack([
        np.stack([val, t, p], 1), np.stack([q, val, p], 1), np.stack([p, val, t], 1),
        np.stack([p, q, val], 1), np.stack([t, p, val], 1), np.stack([val, p, q], 1),
    ])  # fmt: skip
    rgba = np.ones((n_faces, 4), dtype=np.float32)
    rgba[:, :3] = table[sector, i] if n_faces else np.zeros((0, 3))
    return rgba


def set_face_colors(mesh: bpy.types.Mesh, rgba: np.ndarray, name: str = "triangle_index") -> None:
    """Give each face one RGBA colour, stored as a CORNER colour attribute and made active.

    Blender colour attributes live on points or face corners; every corner of face i gets
    colour i, so the viewport's *Attribute* colour mode and the material both show it.
    """
    rgba = np.ascontiguousarray(rgba, dtype=np.float32).reshape(-1, 4)
    totals = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_total", totals)
    starts = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_start", starts)
    per_corner = np.empty((len(mesh.loops), 4), dtype=np.float32)
    corner_face = np.repeat(np.arange(len(totals)), totals)
    corner_index = np.repeat(starts, totals) + (np.arange(totals.sum()) - np.repeat(np.cumsum(totals) - totals, totals))
    per_corner[corner_index] = rgba[corner_face]
    _set_corner_colors(mesh, per_corner, name)


def set_vertex_colors(mesh: bpy.types.Mesh, rgba: np.ndarray, name: str = "correspondence") -> None:
    """Give each vertex an RGBA colour on all its face corners (CORNER attribute, made active)."""
    idx = np.empty(len(mesh.loops), dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", idx)
    per_corner = np.ascontiguousarray(np.asarray(rgba, dtype=np.float32).reshape(-1, 4)[idx])
    _set_corner_colors(mesh, per_corner, name)


def _set_corner_colors(mesh, per_corner: np.ndarray, name: str) -> None:
    attr = mesh.color_attributes.get(name)
    if attr is not None and attr.domain != "CORNER":
        mesh.color_attributes.remove(attr)
        attr = None
    if attr is None:
        attr = mesh.color_attributes.new(name=name, type="FLOAT_COLOR", domain="CORNER")
    attr.data.foreach_set("color", per_corner.ravel())
    mesh.color_attributes.active_color = attr
    index = list(mesh.color_attributes).index(attr)
    mesh.color_attributes.active_color_index = index
    mesh.color_attributes.render_color_index = index


CORRESPONDENCE_ATTRIBUTE = "correspondence"


def colour_correspondence(obj, template_points: np.ndarray, mode: str = "POSITION") -> None:
    """Colour a mesh with the template's topology by correspondence and give it the material.

    ``mode`` "POSITION": a smooth colour by the vertex's place on the template
    (:func:`position_colors` of ``template_points``); "TRIANGLES": one colour per
    triangle index (paper figs. 6-7). Either way corresponding places share a colour on
    the template, every coated instance and the model.
    """
    mesh = obj.data
    if mode == "TRIANGLES":
        set_face_colors(mesh, triangle_index_colors(len(mesh.polygons)), name=CORRESPONDENCE_ATTRIBUTE)
    else:
        set_vertex_colors(mesh, position_colors(template_points), name=CORRESPONDENCE_ATTRIBUTE)
    mat = color_material()
    if not mesh.materials:
        mesh.materials.append(mat)
    else:
        mesh.materials[0] = mat
    show_colour_attributes()


def recolour_scene(context) -> None:
    """Repaint every template, coated and model mesh with the scene's colouring."""
    mode = context.scene.ssm_display.colouring
    template = next((o for o in context.scene.objects if o.type == "MESH" and o.ssm.role == "TEMPLATE"), None)
    stored = load_arrays(template, "ssm_template") if template is not None else None
    points = stored["points_object"] if stored else None
    for obj in context.scene.objects:
        if obj.type == "MESH" and obj.ssm.role in {"TEMPLATE", "COATED", "MODEL", "MODEL_PART", "SAMPLE"}:
            pts = points if points is not None and len(points) == len(obj.data.vertices) else mesh_vertices(obj.data)
            colour_correspondence(obj, pts, mode)


def set_point_attribute(mesh: bpy.types.Mesh, name: str, values: np.ndarray) -> None:
    """Store a per-vertex float attribute (e.g. curvature, variance)."""
    attr = mesh.attributes.get(name)
    if attr is None:
        attr = mesh.attributes.new(name=name, type="FLOAT", domain="POINT")
    attr.data.foreach_set("value", np.ascontiguousarray(values, dtype=np.float32).ravel())


def get_point_attribute(mesh: bpy.types.Mesh, name: str) -> np.ndarray | None:
    """Read a per-vertex float attribute, or None if absent."""
    attr = mesh.attributes.get(name)
    if attr is None:
        return None
    out = np.empty(len(attr.data), dtype=np.float32)
    attr.data.foreach_get("value", out)
    return out


def show_colour_attributes() -> int:
    """Set Solid shading to show the meshes' colour attributes (not the materials' flat grey
    viewport colour), so correspondence colours show in Blender's default shading: every 3D
    viewport and every scene's Workbench render settings that still use the default
    (Material) colouring; a colouring the user chose is left. Returns the viewports set."""
    for scene in bpy.data.scenes:
        if scene.display.shading.color_type == "MATERIAL":
            scene.display.shading.color_type = "VERTEX"
    n = 0
    for screen in bpy.data.screens:
        for area in screen.areas:
            if area.type != "VIEW_3D":
                continue
            for space in area.spaces:
                if space.type == "VIEW_3D" and space.shading.color_type == "MATERIAL":
                    space.shading.color_type = "VERTEX"
                    n += 1
    return n


def color_material(name: str = "SSM Correspondence Colours", attribute: str = "correspondence"):
    """A material that shows the correspondence colour attribute in renders."""
    mat = bpy.data.materials.get(name)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True  # always on (and deprecated) from Blender 5.0
    nodes = mat.node_tree.nodes
    bsdf = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None)
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_name = attribute
    if bsdf is not None:
        mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def new_mesh_object(
    context,
    name: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    collection_name: str | None = None,
    matrix_world: np.ndarray | None = None,
    replace: bool = True,
) -> bpy.types.Object:
    """Create (or replace the data of) the mesh object ``name`` in a collection."""
    obj = bpy.data.objects.get(name) if replace else None
    if obj is not None and obj.type == "MESH":
        mesh_from_arrays(name, vertices, faces, mesh=obj.data)
        if obj.data.shape_keys is not None:
            obj.shape_key_clear()
    else:
        mesh = mesh_from_arrays(name, vertices, faces)
        obj = bpy.data.objects.new(name, mesh)
        coll = ensure_collection(context.scene, collection_name) if collection_name else context.scene.collection
        coll.objects.link(obj)
    if matrix_world is not None:
        set_matrix_world(obj, matrix_world)
    return obj


def set_shape_keys(obj: bpy.types.Object, keys: dict[str, np.ndarray], slider_min=-3.0, slider_max=3.0) -> None:
    """Replace ``obj``'s shape keys by a Basis plus one key per (name, (V, 3) positions)."""
    if obj.data.shape_keys is not None:
        obj.shape_key_clear()
    obj.shape_key_add(name="Basis", from_mix=False)
    for name, positions in keys.items():
        kb = obj.shape_key_add(name=name, from_mix=False)
        kb.data.foreach_set("co", np.ascontiguousarray(positions, dtype=np.float32).ravel())
        kb.slider_min = slider_min
        kb.slider_max = slider_max
        kb.value = 0.0
    obj.data.update()


def evaluated_vertices(context, obj: bpy.types.Object) -> np.ndarray:
    """(V, 3) vertices of the depsgraph-evaluated mesh (shape keys, modifiers applied)."""
    depsgraph = context.evaluated_depsgraph_get()
    depsgraph.update()
    ev = obj.evaluated_get(depsgraph)
    mesh = ev.to_mesh()
    try:
        return mesh_vertices(mesh)
    finally:
        ev.to_mesh_clear()


def select_only(context, objects, *, active=None) -> None:
    """Select exactly ``objects`` in the view layer (every other object deselected).

    ``active``, when given and in the view layer, becomes the active object; otherwise the
    active object stays as it was.
    """
    chosen = {o.name for o in objects if o is not None}
    layer = context.view_layer
    layer.update()  # objects just linked to a collection join the layer's list only then
    for ob in layer.objects:
        ob.select_set(ob.name in chosen)
    if active is not None and active.name in layer.objects:
        layer.objects.active = active


def add_empty(context, name: str, location, parent=None, size: float = 1.5, collection=None) -> bpy.types.Object:
    """A sphere empty at a Blender-world location (mm), optionally parented keeping its place."""
    emp = bpy.data.objects.new(name, None)
    emp.empty_display_type = "SPHERE"
    emp.empty_display_size = size
    coll = collection or (parent.users_collection[0] if parent is not None else context.scene.collection)
    coll.objects.link(emp)
    world = Matrix.Translation(Vector([float(x) for x in location]))
    if parent is not None:
        emp.parent = parent
        emp.matrix_parent_inverse = parent.matrix_world.inverted()
    emp.matrix_world = world
    return emp
