"""The paper's fig. 10 without Blender: the mean and ±2σ of the first modes in three views.

The layout, colours and labels are those of the Blender picture (``operators/render.py``):
columns axial, sagittal, coronal (or the axes a view looks along, for frames that are not
patient axes: then the model is turned as its instances lay in their files,
:func:`~ssm_addon.model.metrics.display_axes`, and the views look along the files' axes); rows the mean (grey), then one row per mode with the shapes
b_k = -2√λ_k (blue) and +2√λ_k (red) of eq. (7) overlaid, opaque, so each colour shows
where its shape reaches further. Here the shapes are drawn by an orthographic z-buffer
rasterizer of our own (numpy), with two-sided Lambert shading and silhouette outlines, so
a ``pip install .`` core writes the figure too.

References
----------
.. [1] "Generation of point based 3D statistical shape models for anatomical objects",
   fig. 10: the mean shape in axial, sagittal and coronal views; the first eigenmode as an
   overlay of the mean and the two shapes deformed along it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .metrics import (
    axis_letters,
    display_axes,
    label_grid_picture,
    modes_figure_labels,
    scale_bar_mm,
    view_names,
    view_orientation,
)
from .pca import ShapeModel

__all__ = ["FIGURE_COLOURS", "FIGURE_VIEWS", "fit_figure", "label_modes_figure", "mode_shapes", "modes_figure_cell",
           "optimisation_figure", "p_value_text", "principal_views", "rasterize_meshes", "render_modes_figure"]

#: Model frame -> screen frame (rows: screen x right, screen y up, towards the viewer).
#: axial: seen from superior (x right, y up); sagittal: from the +x side with z up;
#: coronal: from the +y side with z up.
FIGURE_VIEWS = {
    "axial": np.eye(3),
    "sagittal": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    "coronal": np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),
}
#: RGBA of the mean and of the shapes at -σ and +σ.
FIGURE_COLOURS = {"mean": (0.9, 0.9, 0.88, 1.0), "minus": (0.1, 0.3, 1.0, 1.0), "plus": (1.0, 0.15, 0.1, 1.0)}


def mode_shapes(model: ShapeModel, n_modes: int, sigmas: float) -> list:
    """Rows of (label, [(kind, (N, 3) points mm)]): the mean, then mean ∓ sigmas·√λ_k q_k (eq. 7)."""
    mean = np.asarray(model.mean, float)
    rows = [("mean", [("mean", mean)])]
    for k in range(min(int(n_modes), len(model.variances))):
        step = sigmas * np.sqrt(float(model.variances[k])) * np.asarray(model.modes[k], float)
        rows.append((f"mode {k + 1}", [("minus", mean - step), ("plus", mean + step)]))
    return rows


def rasterize_meshes(meshes, size_px: tuple[int, int], *, background=(1.0, 1.0, 1.0),
                     outline=(0.15, 0.15, 0.15)) -> np.ndarray:
    """Draw triangle meshes given in pixel coordinates with an orthographic z-buffer.

    Parameters
    ----------
    meshes : sequence of (points (N, 3), faces (F, 3), rgb)
        ``points[:, 0]`` pixels right, ``[:, 1]`` pixels down, ``[:, 2]`` depth (larger is
        nearer the viewer); ``rgb`` one colour (3 or 4 values in [0, 1]) or one per face (F, 3).
    size_px : (height, width)

    Returns
    -------
    (height, width, 3) float ndarray in [0, 1]
        Each pixel the nearest triangle covering its centre, shaded 0.35 + 0.65 |n_z|
        (two-sided Lambert, light from the viewer), ``outline`` where the mesh changes
        between neighbouring pixels (None: no outlines).
        Ties in depth go to the earlier mesh and triangle (a stable order, the same on every
        numpy version).
    """
    h, w = int(size_px[0]), int(size_px[1])
    img = np.empty((h, w, 3))
    img[:] = background
    depth_all, key_all, shade_all, owner_all, colour_all = [], [], [], [], []
    for m, (pts, faces, rgb) in enumerate(meshes):
        tri = np.asarray(pts, float)[np.asarray(faces, np.int64)]  # (F, 3, 3)
        face_rgb = np.asarray(rgb, float)
        face_rgb = np.broadcast_to(face_rgb[:3] if face_rgb.ndim == 1 else face_rgb[:, :3], (len(tri), 3))
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12
        tri, n, norm, face_rgb = tri[ok], n[ok], norm[ok], face_rgb[ok]
        shade = 0.35 + 0.65 * np.abs(n[:, 2]) / norm
        x0 = np.clip(np.floor(tri[:, :, 0].min(axis=1)).astype(np.int64), 0, w)
        x1 = np.clip(np.ceil(tri[:, :, 0].max(axis=1)).astype(np.int64), 0, w)
        y0 = np.clip(np.floor(tri[:, :, 1].min(axis=1)).astype(np.int64), 0, h)
        y1 = np.clip(np.ceil(tri[:, :, 1].max(axis=1)).astype(np.int64), 0, h)
        bw, bh = x1 - x0, y1 - y0
        count = bw * bh
        keep = count > 0
        for chunk in np.array_split(np.flatnonzero(keep), max(1, int(count[keep].sum() // 4_000_000) + 1)):
            if not len(chunk):
                continue
            c = count[chunk]
            t = np.repeat(chunk, c)
            off = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
            px = x0[t] + off % bw[t]
            py = y0[t] + off // bw[t]
            cx, cy = px + 0.5, py + 0.5
            a, b, d = tri[t, 0], tri[t, 1], tri[t, 2]
            den = (b[:, 1] - d[:, 1]) * (a[:, 0] - d[:, 0]) + (d[:, 0] - b[:, 0]) * (a[:, 1] - d[:, 1])
            safe = np.where(den != 0, den, 1.0)  # edge-on triangles (den 0) cover no pixel
            l1 = ((b[:, 1] - d[:, 1]) * (cx - d[:, 0]) + (d[:, 0] - b[:, 0]) * (cy - d[:, 1])) / safe
            l2 = ((d[:, 1] - a[:, 1]) * (cx - d[:, 0]) + (a[:, 0] - d[:, 0]) * (cy - d[:, 1])) / safe
            l3 = 1.0 - l1 - l2
            inside = (den != 0) & (l1 >= -1e-9) & (l2 >= -1e-9) & (l3 >= -1e-9)
            if not inside.any():
                continue
            z = l1 * a[:, 2] + l2 * b[:, 2] + l3 * d[:, 2]
            depth_all.append(z[inside])
            key_all.append(py[inside] * w + px[inside])
            shade_all.append(shade[t[inside]])
            colour_all.append(face_rgb[t[inside]])
            owner_all.append(np.full(int(inside.sum()), m))
    if not depth_all:
        return img
    depth, key = np.concatenate(depth_all), np.concatenate(key_all)
    shade, which, rgb_all = np.concatenate(shade_all), np.concatenate(owner_all), np.concatenate(colour_all)
    # per pixel: nearest first, then the earlier fragment (a stable sort of one key: the pixel in
    # the integer part, the depth, scaled into [0, 1), below it; float64 keeps 1e-7 of the depth range)
    near = depth.max()
    span = max(float(near - depth.min()), 1e-12)
    order = np.argsort(key + (near - depth) / (span * (1.0 + 1e-9)), kind="stable")
    first = np.ones(len(order), bool)
    first[1:] = key[order][1:] != key[order][:-1]
    win = order[first]
    flat = img.reshape(-1, 3)
    flat[key[win]] = rgb_all[win] * shade[win, None]
    if outline is None:
        return img
    owner = np.full(h * w, -1)
    owner[key[win]] = which[win]
    owner = owner.reshape(h, w)
    edge = np.zeros((h, w), bool)
    edge[:, 1:] |= owner[:, 1:] != owner[:, :-1]
    edge[1:, :] |= owner[1:, :] != owner[:-1, :]
    img[edge] = outline
    return img


def render_modes_figure(model: ShapeModel, path, n_modes: int = 2, sigmas: float = 2.0, cell_px: int = 320,
                        views=("axial", "sagittal", "coronal")) -> Path:
    """The mean and ±``sigmas``·√λ of the first modes in three views into one PNG (fig. 10).

    Parameters
    ----------
    model : ShapeModel
        ``mean`` and ``modes`` in the model frame (mm), ``faces``, ``variances`` (mm²).
    path : path
        Output PNG.
    n_modes : int
        Rows of modes below the mean row (paper: 2).
    sigmas : float
        b_k = ±sigmas √λ_k (paper: 2).
    cell_px : int
        Pixels per view cell.

    Returns
    -------
    Path
        The PNG written; its picture has the same labels, title and scale bar as Blender's.
    """
    rows = mode_shapes(model, n_modes, sigmas)
    faces = np.asarray(model.faces)
    centre, cell = modes_figure_cell(model, rows)
    px_per_mm = cell_px / cell
    n_rows, n_cols = len(rows), len(views)
    meshes = []
    shown = display_axes(model)  # as the instances lay in their files
    for r, (_label, shapes) in enumerate(rows):
        for c, view in enumerate(views):
            rot = FIGURE_VIEWS[view] @ shown
            for kind, pts in shapes:
                q = (pts - centre) @ rot.T
                screen = np.c_[(c + 0.5) * cell_px + q[:, 0] * px_per_mm, (r + 0.5) * cell_px - q[:, 1] * px_per_mm,
                               q[:, 2]]
                meshes.append((screen, faces, FIGURE_COLOURS[kind]))
    grid = rasterize_meshes(meshes, (n_rows * cell_px, n_cols * cell_px))
    return label_modes_figure(grid, path, model, n_modes=n_modes, sigmas=sigmas, views=views,
                              mm_per_px=cell / float(cell_px))


def modes_figure_cell(model: ShapeModel, rows) -> tuple[np.ndarray, float]:
    """The fig-10 grid's centre (the mean's centroid, model frame mm) and the side of one view
    cell (mm): 1.15 × the diameter of the largest shape drawn (rows of :func:`mode_shapes`)."""
    centre = np.asarray(model.mean, float).mean(axis=0)
    all_pts = np.concatenate([p for _, shapes in rows for _, p in shapes]) - centre
    return centre, 1.15 * 2.0 * float(np.linalg.norm(all_pts, axis=1).max())


def label_modes_figure(grid: np.ndarray, path, model: ShapeModel, *, n_modes: int, sigmas: float, views,
                       mm_per_px: float) -> Path:
    """The fig-10 picture from its drawn grid (Blender's render or :func:`rasterize_meshes`):
    row labels (the mean; each mode's share and colours), column labels (the views and where
    the model's axes point), the title and a scale bar."""
    n_rows = 1 + min(int(n_modes), len(model.variances))
    return label_grid_picture(grid, path, row_labels=modes_figure_labels(model, n_modes, sigmas),
                              column_labels=[f"{name}\n{view_orientation(FIGURE_VIEWS[v], axis_letters(model))}"
                                             for v, name in zip(views, view_names(model, views))],
                              title=f"Mean shape and the first {n_rows - 1} modes (eq. 7, b = ±{sigmas:g}√λ)",
                              mm_per_px=mm_per_px)


def p_value_text(p: float) -> str:
    """A p-value as a paper prints it: two significant figures, ``< 0.001`` or ``> 0.99``, never 0 or 1.

    >>> p_value_text(0.04321), p_value_text(1.0), p_value_text(0.9996), p_value_text(2e-226)
    ('p = 0.043', 'p > 0.99', 'p > 0.99', 'p < 0.001')
    """
    if not np.isfinite(p):
        return "p unknown"
    if p < 0.001:
        return "p < 0.001"
    if p > 0.99:
        return "p > 0.99"
    return f"p = {float(f'{p:.2g}'):g}"


def principal_views(points: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Two views of a shape along its principal axes: ``[(name, screen_from_frame (3, 3))]``.

    The first looks along the axis of least extent, the second along the middle axis; in
    both the longest axis runs across the screen (a long bone lies side-on), and each
    rotation is proper (determinant +1). Signs follow the frame's own axes where they can
    (each principal axis points into the frame's half-space of its largest component), so
    the same shape gives the same views on every library version.
    """
    pts = np.asarray(points, float)
    _w, vecs = np.linalg.eigh(np.cov((pts - pts.mean(axis=0)).T))  # ascending: vecs[:, 0] the least extent
    vecs = vecs * np.sign(vecs[np.argmax(np.abs(vecs), axis=0), np.arange(3)])  # eigh's signs are arbitrary
    long_, mid, least = vecs[:, 2], vecs[:, 1], vecs[:, 0]
    return [("along the least axis", np.stack([long_, mid, np.cross(long_, mid)])),
            ("along the middle axis", np.stack([long_, least, np.cross(long_, least)]))]


def _dress_view(ax, title: str, px_per_mm: float, cell_px: int) -> None:
    """A view's scale bar (mm), title and frame: the pixels of one cell, no axes."""
    bar = scale_bar_mm(1.0 / px_per_mm, cell_px)
    x0, y0 = 0.06 * cell_px, 0.94 * cell_px
    ax.plot([x0, x0 + bar * px_per_mm], [y0, y0], color="black", lw=3, solid_capstyle="butt")
    ax.text(x0, y0 - 0.02 * cell_px, f"{bar:g} mm", fontsize=10, va="bottom")
    ax.set_title(title, fontsize=11)
    ax.set_xlim(0, cell_px)
    ax.set_ylim(cell_px, 0)
    ax.set_axis_off()


def fit_figure(points_mm: np.ndarray, faces: np.ndarray, sd_mm: np.ndarray, target_mm: np.ndarray | None, path, *,
               title: str, summary: str, flagged: bool = False, cell_px: int = 420) -> Path:
    """A fitted shape over its target, in two views along its principal axes (PNG, for a paper).

    The views look along the shape's axis of least extent (its broadest silhouette) and
    along its middle axis, so a long bone is seen side-on in both; the surface is coloured
    by ``sd_mm`` (the posterior SD, mm, with its colour bar), the target's points are
    black dots, and each view has a scale bar.

    Parameters
    ----------
    points_mm : (N, 3) the fitted shape (any frame, mm); faces : (F, 3)
    sd_mm : (N,) posterior SD per point (mm)
    target_mm : (M, 3) or None, the target's points in the same frame
    title, summary : the headline and the line of figures below it (red when ``flagged``)
    """
    import matplotlib
    from matplotlib import cm, colors
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pts = np.asarray(points_mm, float)
    centre = pts.mean(axis=0)
    views = principal_views(pts)
    extent = float(np.linalg.norm(pts - centre, axis=1).max())
    px_per_mm = 0.42 * cell_px / max(extent, 1e-9)
    norm = colors.Normalize(vmin=float(np.min(sd_mm)), vmax=max(float(np.max(sd_mm)), float(np.min(sd_mm)) + 1e-9))
    cmap = matplotlib.colormaps["viridis"]
    face_rgb = cmap(norm(np.asarray(sd_mm, float)[np.asarray(faces)].mean(axis=1)))[:, :3]
    fig = Figure(figsize=(10.4, 5.6), dpi=100)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, 2, i + 1) for i in range(2)]
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.2, top=0.8, wspace=0.04)
    for ax, (name, rot) in zip(axes, views):
        q = (pts - centre) @ rot.T
        screen = np.c_[cell_px / 2 + q[:, 0] * px_per_mm, cell_px / 2 - q[:, 1] * px_per_mm, q[:, 2]]
        img = rasterize_meshes([(screen, faces, face_rgb)], (cell_px, cell_px))
        ax.imshow(img, interpolation="lanczos")
        if target_mm is not None and len(target_mm):
            t = (np.asarray(target_mm, float) - centre) @ rot.T
            ax.scatter(cell_px / 2 + t[:, 0] * px_per_mm, cell_px / 2 - t[:, 1] * px_per_mm, s=1.5, c="black",
                       linewidths=0, alpha=0.6)
        _dress_view(ax, f"view {name}", px_per_mm, cell_px)
    fig.suptitle(title, fontsize=13, y=0.97)
    fig.text(0.5, 0.875, summary, ha="center", fontsize=10.5, color="#b00000" if flagged else "black")
    bar_ax = fig.add_axes([0.12, 0.1, 0.76, 0.03])
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), cax=bar_ax, orientation="horizontal")
    bar_ax.set_xlabel("posterior SD of the fitted surface (mm); black dots: the target's points", fontsize=10)
    path = Path(path)
    fig.savefig(path)
    return path



def optimisation_figure(points_mm: np.ndarray, faces: np.ndarray, movement_mm: np.ndarray, steps, path, *,
                        title: str = "Correspondence optimisation", cell_px: int = 360) -> Path:
    """Where the correspondence optimisation moved points, and its objective by iteration (PNG).

    Left: the objective and the population's entropy (nats) by iteration. Right: the mean
    shape (``points_mm``, model frame) in two views along its principal axes, coloured by
    ``movement_mm``, each point's mean distance from its coated place over the instances (mm,
    with its colour bar).

    Parameters
    ----------
    points_mm : (N, 3) mm; faces : (F, 3)
    movement_mm : (N,) mm
    steps : sequence of :class:`~ssm_addon.correspondence.optimisation.OptimisationStep` (or their dicts)
    """
    import matplotlib
    from matplotlib import cm, colors
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    rows = [s if isinstance(s, dict) else s.to_dict() for s in steps]
    pts = np.asarray(points_mm, float)
    move = np.asarray(movement_mm, float)
    centre = pts.mean(axis=0)
    extent = float(np.linalg.norm(pts - centre, axis=1).max())
    px_per_mm = 0.42 * cell_px / max(extent, 1e-9)
    top = max(float(move.max()) if move.size else 0.0, 1e-6)
    norm = colors.Normalize(vmin=0.0, vmax=top)
    cmap = matplotlib.colormaps["magma_r"]
    face_rgb = cmap(norm(move[np.asarray(faces)].mean(axis=1)))[:, :3] if move.size else None
    fig = Figure(figsize=(13.0, 5.0), dpi=100)
    FigureCanvasAgg(fig)
    curve = fig.add_axes([0.08, 0.22, 0.22, 0.6])
    it = [r["iteration"] for r in rows]
    curve.plot(it, [r["objective"] for r in rows], "o-", color="black", label="objective")
    curve.set_xlabel("iteration")
    curve.xaxis.set_major_locator(MaxNLocator(integer=True))
    curve.set_ylabel("objective")
    twin = curve.twinx()
    twin.plot(it, [r["entropy_nats"] for r in rows], "s--", color="#1f5fbf", label="entropy (nats)")
    twin.set_ylabel("population entropy (nats)", color="#1f5fbf")
    curve.set_title("objective by iteration", fontsize=11)
    lines = curve.get_legend_handles_labels()[0] + twin.get_legend_handles_labels()[0]
    curve.legend(lines, [line.get_label() for line in lines], fontsize=9, loc="upper right")
    for i, (name, rot) in enumerate(principal_views(pts)):
        ax = fig.add_axes([0.36 + 0.31 * i, 0.22, 0.3, 0.66])
        q = (pts - centre) @ rot.T
        screen = np.c_[cell_px / 2 + q[:, 0] * px_per_mm, cell_px / 2 - q[:, 1] * px_per_mm, q[:, 2]]
        rgb = face_rgb if face_rgb is not None else np.full((len(faces), 3), 0.8)
        ax.imshow(rasterize_meshes([(screen, faces, rgb)], (cell_px, cell_px)), interpolation="lanczos")
        _dress_view(ax, f"mean shape, view {name}", px_per_mm, cell_px)
    fig.suptitle(title, fontsize=13, y=0.97)
    bar_ax = fig.add_axes([0.42, 0.1, 0.5, 0.03])
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), cax=bar_ax, orientation="horizontal")
    bar_ax.set_xlabel("each point's mean movement along the surfaces (mm)", fontsize=10)
    path = Path(path)
    fig.savefig(path)
    return path
