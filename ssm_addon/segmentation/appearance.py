"""How the boundary looks along the surface normal: learned profiles, or the image gradient.

Learned appearance follows the active shape models of Cootes et al. (1995, section 4):
for every model point, the image's derivative along its normal is sampled at ``2k + 1``
offsets ``step_mm`` apart; the feature is that profile normalised by the sum of its
absolute values (invariant to a global intensity scale; the feature of Scalismo's active
shape models, so their files and ours share a layout), and the training
profiles give a mean ḡ_i and a covariance S_i per point. A candidate position is scored
by the Mahalanobis distance (g − ḡ_i)ᵀ S_i⁻¹ (g − ḡ_i) (Cootes et al. 1995, eq. 14).
With few training images the covariance of a point pools the profiles of its nearest
neighbours on the mean shape and is shrunk towards the pooled covariance of all points
(Ledoit & Wolf's convex combination), so it is invertible with any number of images.

Without training images the evidence needs no training: the derivative of the image
along the outward normal, negated (a bright object on a darker background, as bone in
CT), at the image blurred to the search's resolution (van Ginneken et al. 2002 compare
both kinds).

References
----------
Cootes TF, Taylor CJ, Cooper DH, Graham J. Active shape models — their training and
application. Computer Vision and Image Understanding 61(1):38–59, 1995.
van Ginneken B, Frangi AF, Staal JJ, ter Haar Romeny BM, Viergever MA. Active shape model
segmentation with optimal features. IEEE Trans Med Imaging 21(8):924–933, 2002.
Ledoit O, Wolf M. A well-conditioned estimator for large-dimensional covariance matrices.
J Multivariate Analysis 88(2):365–411, 2004.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..base.errors import InputError
from ..meshutil import vertex_normals

__all__ = ["Appearance", "LEVEL_SIGMAS_MM", "appearance_from_arrays", "boundary_grey_values", "learn_appearance", "load_appearance", "normalised_derivative",
           "profile_features", "read_scalismo_asm", "write_scalismo_asm"]

LEVEL_SIGMAS_MM = (2.0, 1.0, 0.5)
"""The search's resolutions, coarse to fine: the Gaussian blur (mm) of the image at each level."""
PROFILE_HALF_LENGTH = 4
"""k: a profile holds 2k + 1 samples (the feature 2k derivatives)."""
PROFILE_STEP_MM = 1.0
"""Spacing (mm) of a profile's samples along the normal."""
POOL_NEIGHBOURS = 6
"""A point's covariance pools its profiles with those of this many nearest points on the mean shape."""
SHRINKAGE = 20.0
"""Weight (in samples) of the pooled covariance of all points in each point's covariance."""
DERIVATIVE_STEP_MM = 0.5
"""Half the central difference (mm) that gives a profile sample's derivative along the normal."""
NPZ_PREFIX = "appearance_"


def normalised_derivative(derivatives: np.ndarray) -> np.ndarray:
    """(…, D) derivatives along the normal at a profile's samples, divided by the sum of their
    absolute values (Cootes et al. 1995, section 4.1; Scalismo's normal-direction feature); a flat
    profile gives zeros."""
    d = np.asarray(derivatives, float)
    s = np.abs(d).sum(axis=-1, keepdims=True)
    return d / np.maximum(s, 1e-6)


def boundary_grey_values(image, points, normals, *, sigma_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,), (N,): each point's mean grey value 1–3 mm inside and 1–3 mm outside the surface along its normal
    (the image blurred by ``sigma_mm``): what the boundary separates."""
    inner = image.profiles(points, normals, np.array([-3.0, -2.0, -1.0]), sigma_mm=sigma_mm).mean(axis=1)
    outer = image.profiles(points, normals, np.array([1.0, 2.0, 3.0]), sigma_mm=sigma_mm).mean(axis=1)
    return inner, outer


def profile_features(image, points, normals, offsets_mm, *, sigma_mm: float,
                     h_mm: float = DERIVATIVE_STEP_MM) -> np.ndarray:
    """(N, D) the feature of each point: the image's derivative along the normal (blurred by
    ``sigma_mm``; central difference ±``h_mm``) at each of the offsets (mm), normalised."""
    offsets_mm = np.asarray(offsets_mm, float)
    grid = np.concatenate([offsets_mm - h_mm, offsets_mm + h_mm])
    prof = image.profiles(points, normals, grid, sigma_mm=sigma_mm)
    d = (prof[:, len(offsets_mm):] - prof[:, :len(offsets_mm)]) / (2 * h_mm)
    return normalised_derivative(d)


@dataclass(frozen=True, eq=False)
class Appearance:
    """Per-point profile models at each search level (Cootes et al. 1995).

    Attributes
    ----------
    mean : (L, N, 2k + 1) float
        Mean feature per level and model point.
    covariance : (L, N, 2k + 1, 2k + 1) float
        Its regularised covariance.
    sigmas_mm : (L,) float
        The image blur of each level (mm).
    step_mm : float
        Profile sample spacing (mm).
    boundary_mm : (2,) float
        Mean grey value just inside (1–3 mm) and just outside (1–3 mm) the training surfaces.
    boundary_sd : (2,) float
        Their standard deviations over points and images.
    typical_distance : (L,) float
        Median Mahalanobis distance of the training profiles at the true boundary.
    images : tuple of str
        Names of the training instances whose images taught it.
    voxel_mm : float
        The training images' coarsest voxel edge (mm): images much coarser look otherwise
        (``inf``: not known, a file of another tool).
    profiled : (N,) bool or None
        The points that have a profile model (None: all; another tool may profile a subset).
    scans : int
        How many distinct scans (grey-value images) the profiles were learned from; 0: not recorded.
    """

    mean: np.ndarray
    covariance: np.ndarray
    sigmas_mm: np.ndarray
    step_mm: float
    boundary_mm: np.ndarray
    boundary_sd: np.ndarray
    typical_distance: np.ndarray
    images: tuple = ()
    voxel_mm: float = 1.0
    profiled: np.ndarray | None = None
    scans: int = 0

    @property
    def half_length(self) -> int:
        return (int(self.mean.shape[-1]) - 1) // 2

    @property
    def n_points(self) -> int:
        return int(self.mean.shape[1])

    def level_of(self, level: int) -> int:
        """The stored level that serves the search's ``level`` (a one-level file serves every level)."""
        return min(int(level), len(self.sigmas_mm) - 1)

    def precision(self, level: int) -> np.ndarray:
        """(N, 2k, 2k) inverse covariances of a level (cached)."""
        cache = self.__dict__.setdefault("_precision", {})
        if level not in cache:
            cache[level] = np.linalg.inv(self.covariance[level])
        return cache[level]

    def distance(self, level: int, features: np.ndarray) -> np.ndarray:
        """(N, C) Mahalanobis distances of (N, C, 2k + 1) candidate features from each point's model."""
        level = self.level_of(level)
        d = features - self.mean[level][:, None, :]
        return np.einsum("ncd,nde,nce->nc", d, self.precision(level), d)

    def to_arrays(self) -> dict:
        """The ``appearance_*`` arrays stored in ``model.npz`` beside the shape model."""
        p = NPZ_PREFIX
        return {f"{p}mean": self.mean, f"{p}covariance": self.covariance, f"{p}sigmas_mm": self.sigmas_mm,
                f"{p}step_mm": np.asarray(self.step_mm), f"{p}boundary_mm": self.boundary_mm,
                f"{p}boundary_sd": self.boundary_sd, f"{p}typical_distance": self.typical_distance,
                f"{p}images": np.asarray([str(s) for s in self.images] or np.zeros(0, "<U1")),
                f"{p}voxel_mm": np.asarray(self.voxel_mm), f"{p}scans": np.asarray(int(self.scans))}

    def to_dict(self) -> dict:
        return {"kind": "learned profiles (Cootes et al. 1995)", "images": list(self.images),
                "training_voxel_mm": float(self.voxel_mm),
                "levels_sigma_mm": [float(s) for s in self.sigmas_mm], "step_mm": float(self.step_mm),
                "profile_samples": 2 * self.half_length + 1,
                "boundary_inside_outside": [float(x) for x in self.boundary_mm]}


def appearance_from_arrays(arrays, n_points: int, where: str = "model") -> Appearance | None:
    """The :class:`Appearance` stored in ``arrays`` (an npz's members), or None when it has none."""
    p = NPZ_PREFIX
    if f"{p}mean" not in arrays:
        return None
    mean = np.asarray(arrays[f"{p}mean"], float)
    cov = np.asarray(arrays[f"{p}covariance"], float)
    if mean.ndim != 3 or mean.shape[1] != n_points or cov.shape != mean.shape + (mean.shape[-1],):
        raise InputError(f"{where}: the stored appearance has shape {mean.shape} / {cov.shape}; expected "
                         f"(levels, {n_points}, 2k) and (levels, {n_points}, 2k, 2k)")
    return Appearance(mean=mean, covariance=cov, sigmas_mm=np.asarray(arrays[f"{p}sigmas_mm"], float),
                      step_mm=float(np.asarray(arrays[f"{p}step_mm"]).reshape(-1)[0]), boundary_mm=np.asarray(arrays[f"{p}boundary_mm"], float),
                      boundary_sd=np.asarray(arrays[f"{p}boundary_sd"], float),
                      typical_distance=np.asarray(arrays[f"{p}typical_distance"], float),
                      images=_names(arrays[f"{p}images"]),
                      voxel_mm=float(np.asarray(arrays.get(f"{p}voxel_mm", 1.0)).reshape(-1)[0]),
                      scans=int(np.asarray(arrays.get(f"{p}scans", 0)).reshape(-1)[0]))


def _names(value) -> tuple:
    """The training images' names: an array of str (npz) or a JSON list (a Blender scene's copy)."""
    if isinstance(value, str):
        return tuple(str(s) for s in json.loads(value))
    return tuple(str(s) for s in np.asarray(value).reshape(-1))


def load_appearance(path, n_points: int) -> Appearance | None:
    """The appearance stored in a ``model.npz`` (``allow_pickle=False``) or a statismo file (Scalismo's
    active shape model layout), or None: a model built without images."""
    path = Path(path)
    if not path.is_file():
        return None
    head = path.read_bytes()[:8]
    if head.startswith(b"\x89HDF"):  # a statismo file: ours in full, else Scalismo's active shape model
        return read_own_appearance_h5(path, n_points) or read_scalismo_asm(path, n_points)
    if not head.startswith(b"PK"):
        return None
    with np.load(path, allow_pickle=False) as data:
        if f"{NPZ_PREFIX}mean" not in data.files:
            return None
        arrays = {k: data[k] for k in data.files if k.startswith(NPZ_PREFIX)}
    return appearance_from_arrays(arrays, n_points, str(path))


OWN_GROUP = "ssm/appearance"
"""Where a statismo file written by a build keeps the appearance in full (every level, the training
images and their voxel size: what ``model.npz`` holds), beside Scalismo's one-level active shape model."""


def write_appearance_h5(path, appearance: Appearance) -> None:
    """Put ``appearance`` into a build's statismo file twice: in full under :data:`OWN_GROUP` (the
    ``appearance_*`` arrays of ``model.npz``, so the file segments as ``model.npz`` does) and as
    Scalismo's active shape model (:func:`write_scalismo_asm`, the finest level) for Scalismo."""
    import h5py

    write_scalismo_asm(path, appearance)
    with h5py.File(path, "a") as f:
        if OWN_GROUP in f:
            del f[OWN_GROUP]
        g = f.require_group(OWN_GROUP)
        for key, value in appearance.to_arrays().items():
            value = np.asarray(value)
            if value.dtype.kind == "U":
                g.create_dataset(key, data=json.dumps([str(v) for v in value.reshape(-1)]))
            else:
                g.create_dataset(key, data=value)


def read_own_appearance_h5(path, n_points: int) -> Appearance | None:
    """The appearance a build put in full into its statismo file (:func:`write_appearance_h5`), or None."""
    import h5py

    with h5py.File(path, "r") as f:
        if OWN_GROUP not in f or f"{OWN_GROUP}/{NPZ_PREFIX}mean" not in f:
            return None
        arrays = {}
        for key, ds in f[OWN_GROUP].items():
            value = ds[()]
            arrays[key] = value.decode() if isinstance(value, bytes) else value
    return appearance_from_arrays(arrays, n_points, f"{path}: {OWN_GROUP}")


ASM_GROUP = "/activeShapeModel"
"""Where Scalismo keeps an active shape model in a statismo file (scalismo-asm ``ActiveShapeModelIO``)."""


def write_scalismo_asm(path, appearance: Appearance, *, level: int = -1) -> None:
    """Add ``appearance`` (one level: the finest by default) to a statismo file in the layout of
    Scalismo's active shape models: ``/activeShapeModel`` (attributes majorVersion 1, minorVersion 0)
    with ``imagePreprocessor`` (``builtin::GaussianGradient``, ``stddev`` in mm), ``featureExtractor``
    (``builtin::NormalDirection``, ``numberOfPoints``, ``spacing`` in mm) and ``profiles``
    (``pointIds``, ``means`` (N, D) and ``covariances`` (N·D, D), float32)."""
    import h5py

    lvl = appearance.level_of(level if level >= 0 else len(appearance.sigmas_mm) - 1)
    ids = np.arange(appearance.n_points) if appearance.profiled is None else np.flatnonzero(appearance.profiled)
    d = appearance.mean.shape[-1]
    with h5py.File(path, "a") as f:
        if ASM_GROUP in f:
            del f[ASM_GROUP]
        g = f.create_group(ASM_GROUP)
        g.attrs["majorVersion"] = np.int32(1)
        g.attrs["minorVersion"] = np.int32(0)
        pp = g.create_group("imagePreprocessor")
        for key, value in (("identifier", "builtin::GaussianGradient"), ("majorVersion", np.int32(1)),
                           ("minorVersion", np.int32(0))):
            pp.attrs[key] = value
        pp.create_dataset("stddev", data=np.float32(appearance.sigmas_mm[lvl]))
        fe = g.create_group("featureExtractor")
        for key, value in (("identifier", "builtin::NormalDirection"), ("majorVersion", np.int32(1)),
                           ("minorVersion", np.int32(0))):
            fe.attrs[key] = value
        fe.create_dataset("numberOfPoints", data=np.int32(d))
        fe.create_dataset("spacing", data=np.float32(appearance.step_mm))
        pr = g.create_group("profiles")
        pr.attrs["numberOfPoints"] = np.int32(len(ids))
        pr.attrs["profileLength"] = np.int32(d)
        pr.attrs["comment"] = f"covariances consists of {len(ids)} concatenated {d}x{d} matrices"
        pr.create_dataset("pointIds", data=ids.astype(np.int32))
        pr.create_dataset("means", data=appearance.mean[lvl][ids].astype(np.float32))
        pr.create_dataset("covariances", data=appearance.covariance[lvl][ids].reshape(-1, d).astype(np.float32))


def read_scalismo_asm(path, n_points: int) -> Appearance | None:
    """The active shape model profiles of a statismo file (Scalismo's layout, as
    :func:`write_scalismo_asm` writes it), or None when it has none.

    Raises
    ------
    InputError
        A layout this reader does not know (another preprocessor or feature), named.
    """
    import h5py

    with h5py.File(path, "r") as f:
        if ASM_GROUP not in f:
            return None
        g = f[ASM_GROUP]
        where = f"{path}: {ASM_GROUP}"
        pp, fe, pr = g.get("imagePreprocessor"), g.get("featureExtractor"), g.get("profiles")
        if pp is None or fe is None or pr is None:
            raise InputError(f"{where} lacks imagePreprocessor, featureExtractor or profiles")
        ident = [str(x.attrs.get("identifier", b"")) for x in (pp, fe)]
        ident = [i[2:-1] if i.startswith("b'") else i for i in ident]
        if ident != ["builtin::GaussianGradient", "builtin::NormalDirection"]:
            raise InputError(f"{where}: preprocessor {ident[0]!r} with feature {ident[1]!r}; this reader knows the "
                             "Gaussian gradient along the normal (builtin::GaussianGradient, builtin::NormalDirection)")
        stddev = float(np.asarray(pp["stddev"]))
        d = int(np.asarray(fe["numberOfPoints"]))
        spacing = float(np.asarray(fe["spacing"]))
        ids = np.asarray(pr["pointIds"], np.int64).reshape(-1)
        means = np.asarray(pr["means"], float).reshape(len(ids), d)
        covs = np.asarray(pr["covariances"], float).reshape(len(ids), d, d)
    if d % 2 != 1 or len(ids) == 0 or ids.min() < 0 or ids.max() >= n_points:
        raise InputError(f"{where}: {len(ids)} profiles of length {d} for a model of {n_points} points")
    mean = np.zeros((1, n_points, d))
    cov = np.broadcast_to(np.eye(d), (1, n_points, d, d)).copy()
    mean[0, ids], cov[0, ids] = means, 0.5 * (covs + covs.transpose(0, 2, 1))
    profiled = np.zeros(n_points, bool)
    profiled[ids] = True
    return Appearance(mean=mean, covariance=cov, sigmas_mm=np.array([stddev]), step_mm=spacing,
                      boundary_mm=np.array([np.nan, np.nan]), boundary_sd=np.array([np.nan, np.nan]),
                      typical_distance=np.array([float(d)]), images=(f"{path.name} (active shape model)",),
                      voxel_mm=float("inf"), profiled=profiled)


def _regularised(samples: np.ndarray, pooled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (N, D) and shrunk covariance (N, D, D) of (N, S, D) samples per point."""
    m = samples.mean(axis=1)
    d = samples - m[:, None, :]
    n_s = samples.shape[1]
    local = np.einsum("nsd,nse->nde", d, d) / max(n_s - 1, 1)
    cov = (n_s * local + SHRINKAGE * pooled[None]) / (n_s + SHRINKAGE)
    ridge = 1e-4 * np.trace(pooled) / pooled.shape[0]
    return m, cov + ridge * np.eye(pooled.shape[0])[None]


def learn_appearance(mean_shape: np.ndarray, faces: np.ndarray, shapes_world: list, images: list, *,
                     names=(), sigmas_mm=LEVEL_SIGMAS_MM, half_length: int = PROFILE_HALF_LENGTH,
                     step_mm: float = PROFILE_STEP_MM) -> Appearance:
    """Learn the boundary's profiles from training shapes in their images.

    Parameters
    ----------
    mean_shape : (N, 3) mm
        The model's mean (model frame): it decides each point's neighbours for pooling.
    faces : (F, 3) int
        The model's triangles (outward normals).
    shapes_world : list of (N, 3) mm
        Each training instance's corresponding points in its image's world frame (RAS).
    images : list of GreyImage
        The images, one per shape.
    names : sequence of str
        The instances' names (stored, for the report).
    sigmas_mm, half_length, step_mm
        The levels' blur (mm), k, and the profile spacing (mm).

    Returns
    -------
    Appearance
    """
    if not shapes_world or len(shapes_world) != len(images):
        raise InputError("appearance: one image is needed per training shape")
    mean_shape = np.asarray(mean_shape, float)
    n = len(mean_shape)
    offsets = step_mm * np.arange(-half_length, half_length + 1)
    near = cKDTree(mean_shape).query(mean_shape, k=min(POOL_NEIGHBOURS + 1, n))[1]
    means, covs, typical = [], [], []
    inside, outside = [], []
    shapes = [np.asarray(pts, float) for pts in shapes_world]
    normals = [vertex_normals(pts, faces) for pts in shapes]
    for level, sigma in enumerate(sigmas_mm):
        feats = []
        for pts, nrm, img in zip(shapes, normals, images):
            feats.append(profile_features(img, pts, nrm, offsets, sigma_mm=sigma))
            if level == len(sigmas_mm) - 1:
                inner, outer = boundary_grey_values(img, pts, nrm, sigma_mm=sigma)
                inside.append(inner)
                outside.append(outer)
        f = np.stack(feats, axis=1)  # (N, n_images, D)
        pooled_samples = f[near].reshape(n, -1, f.shape[-1])  # (N, (P+1)·n_images, D)
        allc = f.reshape(-1, f.shape[-1])
        pooled = np.cov(allc.T) if len(allc) > 1 else np.eye(f.shape[-1]) * 1e-2
        m, c = _regularised(pooled_samples, pooled)
        means.append(m)
        covs.append(c)
        d = f - m[:, None, :]
        dist = np.einsum("nsd,nde,nse->ns", d, np.linalg.inv(c), d)
        typical.append(float(np.median(dist)))
    ins, outs = np.concatenate(inside), np.concatenate(outside)
    return Appearance(mean=np.stack(means), covariance=np.stack(covs), sigmas_mm=np.asarray(sigmas_mm, float),
                      step_mm=float(step_mm), boundary_mm=np.array([ins.mean(), outs.mean()]),
                      boundary_sd=np.array([ins.std(), outs.std()]), typical_distance=np.asarray(typical),
                      images=tuple(str(s) for s in names),
                      voxel_mm=float(max(float(img.spacing_mm.max()) for img in images)),
                      scans=len({id(img) for img in images}))
