"""A built-in population of synthetic vertebra-like shapes with known variation modes.

Each shape is the zero level set of a smooth implicit function in a *canonical* frame
(mm; x to the patient's right, y anterior, z superior): a vertebral body (capped
cylinder), the neural arch (a torus around the vertebral foramen, so every shape is a
closed genus-1 solid like a real lumbar vertebra), a spinous process and two transverse
processes (capsules), joined by a polynomial smooth minimum. Four parameters vary with
known standard deviations (the demo's "true" modes): body height, body radius, spinous
process length and transverse process length. Each instance is posed with a small random
rotation and translation, sampled into an anisotropic oblique grid (0.8 × 0.8 × 1.5 mm by
default, stored LPS-like with a tilted affine) and saved as a NIfTI label map (label 20 for
the vertebra, 21 for a piece of the neighbouring vertebra's body) plus a landmark file at
13 analytic extremal points (exact correspondences). The landmark formats rotate through
Slicer ``.fcsv`` (LPS), Slicer ``.mrk.json`` (LPS), ``.csv`` (world RAS) and a
Scalismo-style ``.json`` (world RAS), so the demo exercises every reader.

Each instance also has attributes with a known relation to its shape, for the analysis
(``[analysis]`` in the project): ``group`` is "long" where the spinous process is longer
than the mean and "short" otherwise, and ``age`` (years) is 60 + 10 × the transverse
process's standardised length + noise of 3 years, so transverse process length follows
age by about 0.3 mm per year. ``truth.json`` holds the values and the effects.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
from scipy.special import chdtrc

from ..formats.landmarks import LandmarkSet, write_landmarks

VERTEBRA_LABEL = 20
NEIGHBOUR_LABEL = 21

#: Overall size: 1.2 gives a lumbar-sized vertebra (body about 48 mm wide, 31 mm high)
#: whose default template has about the paper's 600 points at 1 mm.
SIZE = 1.2

#: Mean and standard deviation (mm) of the varying shape parameters (the known modes).
MODES = {
    "body_height": (26.0 * SIZE, 2.0 * SIZE),
    "body_radius": (20.0 * SIZE, 1.5 * SIZE),
    "spinous_length": (24.0 * SIZE, 3.0 * SIZE),
    "transverse_length": (20.0 * SIZE, 2.5 * SIZE),
}

# Fixed geometry (mm).
RING_RADIUS = 13.0 * SIZE  # torus major radius (foramen centre to arch tube centre)
RING_TUBE = 4.5 * SIZE  # torus minor radius (arch thickness / 2)
SPINOUS_RADIUS = 4.0 * SIZE
TRANSVERSE_RADIUS = 3.5 * SIZE
BODY_GAP = 3.0 * SIZE  # body's posterior wall this far anterior of the foramen's anterior wall
SMOOTH_MM = 1.5 * SIZE  # smooth-minimum width

LANDMARK_FORMATS = (".fcsv", ".mrk.json", ".csv", ".json")


@dataclass(frozen=True)
class ShapeParams:
    """Parameters of one synthetic vertebra (mm)."""

    body_height: float
    body_radius: float
    spinous_length: float
    transverse_length: float

    @property
    def body_centre_y(self) -> float:
        """y (mm, canonical) of the body's axis: its posterior wall sits BODY_GAP in front of the foramen."""
        return RING_RADIUS - RING_TUBE + BODY_GAP + self.body_radius

    def segments(self):
        """Spinous and transverse process axes as (start, end, radius) in canonical mm."""
        ls, lt = self.spinous_length, self.transverse_length
        a, b = 1.0 * SIZE, 2.0 * SIZE
        sp = (np.array([0.0, -(RING_RADIUS + b), 0.0]), np.array([0.0, -(RING_RADIUS + b + ls), -0.35 * ls]))
        tr = (np.array([RING_RADIUS + a, -b, 0.0]), np.array([RING_RADIUS + a + lt, -6.0 * SIZE, b]))
        tl = (tr[0] * [-1, 1, 1], tr[1] * [-1, 1, 1])
        return [(*sp, SPINOUS_RADIUS), (*tr, TRANSVERSE_RADIUS), (*tl, TRANSVERSE_RADIUS)]


def _smin(a: np.ndarray, b: np.ndarray, k: float = SMOOTH_MM) -> np.ndarray:
    """Polynomial smooth minimum: exact min where |a - b| >= k."""
    h = np.clip(k - np.abs(a - b), 0.0, None) / k
    return np.minimum(a, b) - h * h * k / 4.0


def _capsule(x, y, z, a: np.ndarray, b: np.ndarray, r: float):
    ab = b - a
    t = np.clip(((x - a[0]) * ab[0] + (y - a[1]) * ab[1] + (z - a[2]) * ab[2]) / float(ab @ ab), 0.0, 1.0)
    return np.sqrt((x - a[0] - t * ab[0]) ** 2 + (y - a[1] - t * ab[1]) ** 2 + (z - a[2] - t * ab[2]) ** 2) - r


def _cylinder_z(x, y, z, centre, radius: float, half_height: float):
    dr = np.hypot(x - centre[0], y - centre[1]) - radius
    dz = np.abs(z - centre[2]) - half_height
    return np.minimum(np.maximum(dr, dz), 0.0) + np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0))


def vertebra_sdf(points: np.ndarray, shape: ShapeParams) -> np.ndarray:
    """Approximate signed distance (mm, negative inside) of canonical points (M, 3) to the shape."""
    x, y, z = np.asarray(points).T
    ring = np.hypot(np.hypot(x, y) - RING_RADIUS, z) - RING_TUBE
    body = _cylinder_z(x, y, z, (0.0, shape.body_centre_y, 0.0), shape.body_radius, shape.body_height / 2)
    d = _smin(ring, body)
    for a, b, r in shape.segments():
        d = _smin(d, _capsule(x, y, z, a, b, r))
    return d


def neighbour_sdf(points: np.ndarray, shape: ShapeParams) -> np.ndarray:
    """The body of the next vertebra down (a cylinder below a 7 mm disc), canonical mm."""
    x, y, z = np.asarray(points).T
    centre = (0.0, shape.body_centre_y, -shape.body_height - 6.0 * SIZE)
    return _cylinder_z(x, y, z, centre, shape.body_radius, shape.body_height / 2)


def landmarks_canonical(shape: ShapeParams) -> dict[str, np.ndarray]:
    """13 named extremal surface points (canonical mm), exact on the implicit surface."""
    yb, rb, hh = shape.body_centre_y, shape.body_radius, shape.body_height / 2
    inner = RING_RADIUS - RING_TUBE
    diag = RING_RADIUS / np.sqrt(2.0)
    out = {
        "body_anterior": [0.0, yb + rb, 0.0],
        "body_right": [rb, yb, 0.0],
        "body_left": [-rb, yb, 0.0],
        "body_superior": [0.0, yb, hh],
        "body_inferior": [0.0, yb, -hh],
        "foramen_posterior": [0.0, -inner, 0.0],
        "foramen_right": [inner, 0.0, 0.0],
        "foramen_left": [-inner, 0.0, 0.0],
        "lamina_right": [diag, -diag, RING_TUBE],
        "lamina_left": [-diag, -diag, RING_TUBE],
    }
    for name, (a, b, r) in zip(("spinous_tip", "transverse_right_tip", "transverse_left_tip"), shape.segments()):
        u = (b - a) / np.linalg.norm(b - a)
        out[name] = b + r * u
    return {k: np.asarray(v, float) for k, v in out.items()}


def canonical_box(shape: ShapeParams, margin_mm: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) canonical mm corners of a box holding the vertebra with a margin."""
    lo = np.array([-(RING_RADIUS + SIZE + shape.transverse_length + TRANSVERSE_RADIUS),
                   -(RING_RADIUS + 2 * SIZE + shape.spinous_length + SPINOUS_RADIUS),
                   min(-shape.body_height / 2, -0.35 * shape.spinous_length - SPINOUS_RADIUS)])
    hi = np.array([-lo[0], shape.body_centre_y + shape.body_radius, shape.body_height / 2])
    return lo - margin_mm, hi + margin_mm


def _rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(-max_deg, max_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _grid_affine(corners_world: np.ndarray, spacing: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Affine (voxel -> world) of a grid with ``direction`` columns covering ``corners_world``."""
    lin = direction * spacing
    ijk = (corners_world @ np.linalg.inv(lin).T)
    lo, hi = np.floor(ijk.min(axis=0)) - 1, np.ceil(ijk.max(axis=0)) + 1
    affine = np.eye(4)
    affine[:3, :3] = lin
    affine[:3, 3] = lin @ lo
    return affine, tuple(int(x) for x in hi - lo + 1)


def pose_matrix(rot: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(4, 4) canonical mm -> world mm."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, shift
    return m


def rasterize(sdf, dims, voxel_to_canon: np.ndarray, block: int = 4) -> np.ndarray:
    """Boolean grid ``sdf(canonical points) <= 0`` at voxel centres, coarse-to-fine.

    The implicit functions are (close to) distance bounds, so a ``block``³ voxel block
    whose centre lies farther from the surface than the block's half diagonal is
    uniformly inside or outside; only the other blocks are evaluated voxel by voxel.
    """
    lin = voxel_to_canon[:3, :3].astype(np.float32)
    off = voxel_to_canon[:3, 3].astype(np.float32)
    nb = [-(-d // block) for d in dims]
    centres = np.stack(np.meshgrid(*(np.arange(n, dtype=np.float32) * block + (block - 1) / 2 for n in nb),
                                   indexing="ij"), -1).reshape(-1, 3)
    d = sdf(centres @ lin.T + off)
    half_diag = 0.5 * block * float(np.linalg.norm(np.linalg.norm(lin, axis=0))) + 0.5
    coarse = (d <= 0).reshape(nb)
    near = np.flatnonzero(np.abs(d) <= half_diag)
    full = np.repeat(np.repeat(np.repeat(coarse, block, 0), block, 1), block, 2)
    bi = np.stack(np.unravel_index(near, nb), -1)
    steps = np.stack(np.meshgrid(*(np.arange(block),) * 3, indexing="ij"), -1).reshape(-1, 3)
    ijk = (bi[:, None, :] * block + steps[None]).reshape(-1, 3)
    full[tuple(ijk.T)] = sdf(ijk.astype(np.float32) @ lin.T + off) <= 0
    return full[: dims[0], : dims[1], : dims[2]]


def make_demo_population(
    out_dir, *, n: int = 24, seed: int = 0, spacing_mm: float = 1.0, voxel_mm=(0.8, 0.8, 1.5)
) -> Path:
    """Generate ``n`` synthetic vertebra label maps, landmark files and a project file.

    Parameters
    ----------
    out_dir : path
        Folder to write into (created if needed).
    n : int
        Number of instances (>= 3).
    seed : int
        Seed of the shape parameters and poses (same seed, same files).
    spacing_mm : float
        Isotropic resampling spacing (mm) written into the project's ``[template]``.
    voxel_mm : float or (3,) floats
        Voxel size of the label maps in mm (anisotropic by default, like CT).

    Returns
    -------
    Path
        The project file ``out_dir/project.toml``. ``out_dir/truth.json`` holds each
        instance's shape parameters, pose (canonical -> world) and the modes' standard
        deviations.
    """
    if n < 3:
        raise ValueError("the demo needs at least 3 instances")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    spacing = np.broadcast_to(np.asarray(voxel_mm, float), (3,)).copy()
    width = max(2, len(str(n - 1)))
    names = [f"demo_{i:0{width}d}" for i in range(n)]
    b = rng.normal(size=(n, len(MODES)))
    b = np.clip(b, -2.5, 2.5)
    shapes = [ShapeParams(**{k: m + s * bi for (k, (m, s)), bi in zip(MODES.items(), row)}) for row in b]
    # A tilted, LPS-stored scanner grid shared by all scans (like one CT protocol).
    direction = _rotation(np.random.default_rng(seed + 1000), 12.0) @ np.diag([-1.0, -1.0, 1.0])
    truth = {"modes": {k: {"mean_mm": m, "sd_mm": s} for k, (m, s) in MODES.items()}, "instances": []}
    lines = [
        "# SSM Builder demo: synthetic vertebra-like shapes with four known modes (see truth.json).",
        "# Generated by `python -m ssm_addon demo`; paths are relative to this file.",
        "",
        "[template]",
        f'instance = "{names[int(np.argmin(np.linalg.norm(b, axis=1)))]}"',
        f"spacing = {float(spacing_mm)}",
        "",
        "[coating]",
        "",
        "[model]",
        'alignment = "none"',
        "",
    ]
    for i, (name, shape) in enumerate(zip(names, shapes)):
        rot = _rotation(rng, 10.0)
        shift = rng.uniform(-15.0, 15.0, size=3) + [0.0, 0.0, -40.0 * i]
        # Canonical bounding box (mm) with a margin, posed into world.
        lo, hi = canonical_box(shape, margin_mm=4.0)
        lo[2] = -shape.body_height - 4.0  # include part of the neighbour below
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        affine, dims = _grid_affine(corners @ rot.T + shift, spacing, direction)
        to_canon = np.linalg.inv(pose_matrix(rot, shift)) @ affine
        labels = np.zeros(dims, np.uint8)
        labels[rasterize(lambda q, s=shape: neighbour_sdf(q, s), dims, to_canon)] = NEIGHBOUR_LABEL
        labels[rasterize(lambda q, s=shape: vertebra_sdf(q, s), dims, to_canon)] = VERTEBRA_LABEL
        img = nib.Nifti1Image(labels, affine)
        img.set_qform(affine, code=1)
        img.set_sform(affine, code=1)
        nib.save(img, out / f"{name}.nii.gz")
        lm = landmarks_canonical(shape)
        lm_world = np.array(list(lm.values())) @ rot.T + shift
        fmt = LANDMARK_FORMATS[i % len(LANDMARK_FORMATS)]
        write_landmarks(out / f"{name}{fmt}", LandmarkSet(tuple(lm), lm_world, source=name))
        pose = pose_matrix(rot, shift)
        truth["instances"].append(
            {"name": name, "b": b[i].tolist(), "shape": asdict(shape), "canonical_to_world": pose.tolist()}
        )
        lines += [
            "[[instances]]",
            f'name = "{name}"',
            f'volume = "{name}.nii.gz"',
            f"label = {VERTEBRA_LABEL}",
            f'landmarks = "{name}{fmt}"',
            "",
        ]
    # attributes with a known effect on shape (their own random stream: the shapes are unchanged)
    age = 60.0 + 10.0 * b[:, 3] + np.random.default_rng(seed + 2000).normal(scale=3.0, size=n)
    group = np.where(b[:, 2] > 0, "long", "short")
    if len(set(group)) < 2 or min(np.sum(group == "long"), np.sum(group == "short")) < 2:
        group = np.where(b[:, 2] > np.median(b[:, 2]), "long", "short")
    tl = np.array([s.transverse_length for s in shapes])
    sl = np.array([s.spinous_length for s in shapes])
    truth["attributes"] = {
        "group": "long where the spinous process is longer than the mean, short otherwise",
        "age": "60 + 10 b_transverse + N(0, 3^2) years",
        "spinous_length_difference_mm": float(sl[group == "long"].mean() - sl[group == "short"].mean()),
        "transverse_length_per_year_mm": float(np.polyfit(age, tl, 1)[0]),
    }
    for i, rec in enumerate(truth["instances"]):
        rec["attributes"] = {"group": str(group[i]), "age": round(float(age[i]), 1)}
    lines[lines.index("[[instances]]"):lines.index("[[instances]]")] = [
        "[analysis]", 'group = "group"', 'covariates = ["age"]', ""]
    out_lines = []
    k = 0
    for line in lines:
        out_lines.append(line)
        if line.startswith("landmarks = "):
            a = truth["instances"][k]["attributes"]
            out_lines.append(f'attributes = {{ group = "{a["group"]}", age = {a["age"]} }}')
            k += 1
    lines = out_lines
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    project = out / "project.toml"
    project.write_text("\n".join(lines))
    return project


def explain_findings(report_path, truth_path) -> list[str]:
    """The demo's findings read against its truth: for each instance a gate named, how far its true
    shape parameters lie from the mean (SD: the largest one, and all together, whose square is a
    chi-square of as many degrees of freedom as parameters) and whether that is the population's
    edge (one parameter beyond 2 SD, or all together farther than 90 % of a normal population),
    as lines to print."""
    report = json.loads(Path(report_path).read_text())
    truth = json.loads(Path(truth_path).read_text())
    modes = list(truth["modes"])
    b = {inst["name"]: np.asarray(inst["b"], float) for inst in truth["instances"]}
    findings = report.get("quality", {}).get("findings", []) if isinstance(report.get("quality"), dict) else []
    extreme = {n: float(np.abs(v).max()) for n, v in b.items()}
    ranked = sorted(extreme, key=lambda n: -extreme[n])
    overall = {n: float(np.linalg.norm(v)) for n, v in b.items()}
    ranked_all = sorted(overall, key=lambda n: -overall[n])
    lines = []
    for name in sorted({f.get("instance") for f in findings if f.get("instance") in b}):
        gates = sorted({f["gate"] for f in findings if f.get("instance") == name})
        k = int(np.argmax(np.abs(b[name])))
        rank = ranked.index(name) + 1
        farther = float(chdtrc(len(b[name]), overall[name] ** 2))  # share of a normal population farther
        edge = extreme[name] >= 2.0 or farther < 0.10
        where = "at the population's edge" if edge else "not at the population's edge"
        order = "the most extreme" if rank == 1 else f"number {rank} by extremity"
        together = ""
        if len(b[name]) > 1:
            together = (f"; all {len(b[name])} together {overall[name]:.2f} SD from the mean, number "
                        f"{ranked_all.index(name) + 1}, {100 * farther:.0f} % of a normal population farther")
        why = ", so the model of the others reconstructs it poorly" if edge and "reconstruction" in gates else ""
        verdict = "; expected of a random population, not a fault" if edge else "; look at it"
        lines.append(f"demo: {name} [{', '.join(gates)}] is {where}: its true {modes[k]} is {b[name][k]:+.2f} SD "
                     f"(truth.json; {order} of {len(b)}{together}){why}{verdict} (report.html, Instances: {name})")
    return lines
