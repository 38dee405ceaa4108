"""The model's files: ``model.npz`` (the contract) and statismo HDF5."""

from __future__ import annotations

import csv
import datetime
import io
import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..base.errors import InputError
from ..base.records import jsonable
from ..formats.gltf import write_glb
from ..formats.vtk import write_vtk, write_vtp
from ..model.joint import joined_parts
from ..model.metrics import display_axes
from ..model.pca import EMPTY_MODE_SHARE, ShapeModel, drop_empty_modes
from ..version import __version__

NPZ_KEYS = (
    "mean",
    "faces",
    "modes",
    "variances",
    "instance_names",
    "instance_points",
    "instance_points_world",
    "params_json",
)
"""The arrays of ``model.npz`` (the file contract; ``allow_pickle=False``)."""


# ---------------------------------------------------------------------------------------
# Files: model.npz (contract) and statismo HDF5
# ---------------------------------------------------------------------------------------
def save_npz(model: ShapeModel, path, extra: dict | None = None) -> Path:
    """Write ``model.npz`` per the contract (no pickled objects; names as fixed-width unicode).

    Keys: mean (N,3), faces (F,3), modes (K,N,3), variances (K,), instance_names (n,),
    instance_points (n,N,3), instance_points_world (n,N,3), params_json (0-d str); ``extra``:
    further arrays stored beside them (e.g. the learned appearance's ``appearance_*``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = np.asarray([str(s) for s in model.instance_names])
    if names.size == 0:
        names = np.zeros(0, dtype="<U1")
    arrays = {
        "mean": np.asarray(model.mean, dtype=float),
        "faces": np.asarray(model.faces, dtype=np.int64),
        "modes": np.asarray(model.modes, dtype=float),
        "variances": np.asarray(model.variances, dtype=float),
        "instance_names": names,
        "instance_points": np.asarray(model.instance_points, dtype=float),
        "instance_points_world": np.asarray(model.instance_points_world, dtype=float),
        "params_json": np.asarray(json.dumps(jsonable(model.params), sort_keys=True)),
    }
    if model.structure_names:  # a joint model: its structures' point ranges
        arrays["structure_names"] = np.asarray([str(s) for s in model.structure_names])
        arrays["structure_offsets"] = np.asarray(model.structure_offsets, dtype=np.int64)
    arrays.update(extra or {})
    write_npz(path, arrays)
    return path


def write_npz(path, arrays: dict) -> Path:
    """``np.savez`` with fixed member dates: the same arrays give the same bytes.

    ``np.savez`` stamps every member with the current time, so two identical builds
    would differ; here each ``<key>.npy`` member has the zip epoch (1980-01-01). The file
    reads with ``np.load(path, allow_pickle=False)``.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for key, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    os.replace(tmp, path)
    return path


def model_from_arrays(arrays: dict, where: str = "model") -> ShapeModel:
    """Check shapes of the model arrays and make a ShapeModel (errors name ``where``)."""
    mean = np.asarray(arrays["mean"], dtype=float)
    if mean.ndim != 2 or mean.shape[1] != 3:
        raise InputError(f"{where}: 'mean' has shape {mean.shape}; expected (N, 3)")
    npts = mean.shape[0]
    faces = np.asarray(arrays["faces"])
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise InputError(f"{where}: 'faces' has shape {faces.shape} dtype {faces.dtype}; expected (F, 3) integers")
    if faces.size and (faces.min() < 0 or faces.max() >= npts):
        raise InputError(f"{where}: 'faces' index points outside 0..{npts - 1}")
    modes = np.asarray(arrays["modes"], dtype=float)
    if modes.ndim != 3 or modes.shape[1:] != (npts, 3):
        raise InputError(f"{where}: 'modes' has shape {modes.shape}; expected (K, {npts}, 3)")
    variances = np.asarray(arrays["variances"], dtype=float)
    if variances.shape != (modes.shape[0],):
        raise InputError(f"{where}: 'variances' has shape {variances.shape}; expected ({modes.shape[0]},)")
    if np.any(variances < 0) or np.any(np.diff(variances) > 1e-12 * max(variances.max(initial=0), 1.0)):
        raise InputError(f"{where}: 'variances' must be non-negative and descending")
    names = np.asarray(arrays["instance_names"]).astype(str)
    if names.ndim != 1:
        raise InputError(f"{where}: 'instance_names' has shape {names.shape}; expected (n,)")
    n = names.shape[0]
    pts = np.asarray(arrays["instance_points"], dtype=float)
    world = np.asarray(arrays["instance_points_world"], dtype=float)
    for key, arr in (("instance_points", pts), ("instance_points_world", world)):
        if arr.shape != (n, npts, 3):
            raise InputError(f"{where}: '{key}' has shape {arr.shape}; expected ({n}, {npts}, 3)")
    for key, arr in (("mean", mean), ("modes", modes), ("variances", variances), ("instance_points", pts),
                     ("instance_points_world", world)):
        if arr.size and not np.all(np.isfinite(arr)):
            bad = int(np.sum(~np.isfinite(arr)))
            raise InputError(f"{where}: '{key}' holds {bad} NaN or infinite value(s); the model is damaged")
    params = arrays.get("params", {})
    structures, offsets = (), None
    if arrays.get("structure_names") is not None and len(arrays["structure_names"]):
        structures = tuple(str(s) for s in np.asarray(arrays["structure_names"]).reshape(-1))
        offsets = np.asarray(arrays.get("structure_offsets"), dtype=np.int64).reshape(-1)
        if (len(offsets) != len(structures) + 1 or offsets[0] != 0 or offsets[-1] != npts
                or np.any(np.diff(offsets) <= 0)):
            raise InputError(f"{where}: 'structure_offsets' {offsets.tolist()} do not split the {npts} points into "
                             f"the structures {', '.join(structures)}")
    return ShapeModel(
        mean=mean,
        faces=faces.astype(np.int64),
        modes=modes,
        variances=variances,
        instance_names=names,
        instance_points=pts,
        instance_points_world=world,
        params=params,
        structure_names=structures,
        structure_offsets=offsets,
    )


def load_npz(path) -> ShapeModel:
    """Read a ``model.npz`` written by :func:`save_npz` (``allow_pickle=False``).

    Raises
    ------
    InputError
        The file is missing, not an npz, lacks a key or has arrays of the wrong shape.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: model file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in NPZ_KEYS if k not in data.files]
            if missing:
                raise InputError(f"{path}: not a model.npz, missing keys {missing}")
            arrays = {k: data[k] for k in NPZ_KEYS}
            for k in ("structure_names", "structure_offsets"):
                if k in data.files:
                    arrays[k] = data[k]
    except InputError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        raise InputError(f"{path}: damaged or not a model .npz ({type(err).__name__}: {err}); rebuild it or "
                         "copy it again") from None
    try:
        params = json.loads(str(arrays.pop("params_json")))
    except json.JSONDecodeError as err:
        raise InputError(f"{path}: 'params_json' is not valid JSON ({err})") from err
    if not isinstance(params, dict):
        raise InputError(f"{path}: 'params_json' is not a JSON object")
    arrays["params"] = params
    return model_from_arrays(arrays, str(path))


def save_statismo(model: ShapeModel, path, noise_variance: float = 0.0) -> Path:
    """Write the model as a statismo 0.9 HDF5 file (readable by statismo and Scalismo).

    Layout (statismo 0.9 / Scalismo ``StatismoIO``): ``/version/majorVersion`` = 0,
    ``/version/minorVersion`` = 9; ``/model/mean`` (3N,) float32 (point positions);
    ``/model/pcaBasis`` (3N, K) float32 with the *orthonormal* eigenvectors as columns
    (version 0.9; 0.8 stored them scaled by √λ); ``/model/pcaVariance`` (K,) the
    eigenvalues (mm²); ``/model/noiseVariance`` scalar; ``/representer`` with attributes
    ``name`` = "itkStandardMeshRepresenter", ``datasetType`` = "POLYGON_MESH" and datasets
    ``points`` (3, N) float32 (the mean as reference) and ``cells`` (3, F) int32;
    ``/modelinfo`` with ``build-time``, ``scores`` (K, n) and ``modelBuilder-0`` (builder
    name, build time, ``parameters`` and ``dataInfo``). SSM Builder's extras (instance names
    and points, the JSON parameters) go into ``/ssm``, which other readers ignore.
    """
    import h5py

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    k = model.n_modes
    build_time = str(model.params.get("created", datetime.datetime.now().isoformat()))
    with h5py.File(path, "w") as f:
        ver = f.create_group("version")
        ver.create_dataset("majorVersion", data=np.int32(0))
        ver.create_dataset("minorVersion", data=np.int32(9))
        g = f.create_group("model")
        g.create_dataset("mean", data=model.mean.reshape(-1).astype(np.float32))
        g.create_dataset("pcaBasis", data=model.modes.reshape(k, -1).T.astype(np.float32))
        g.create_dataset("pcaVariance", data=model.variances.astype(np.float32))
        g.create_dataset("noiseVariance", data=np.float32(noise_variance))
        rep = f.create_group("representer")
        rep.attrs["name"] = "itkStandardMeshRepresenter"
        rep.attrs["datasetType"] = "POLYGON_MESH"
        rep.attrs["version/majorVersion"] = "0"
        rep.attrs["version/minorVersion"] = "9"
        rep.create_dataset("points", data=model.mean.T.astype(np.float32))
        rep.create_dataset("cells", data=np.asarray(model.faces, dtype=np.int32).T)
        info = f.create_group("modelinfo")
        info.create_dataset("build-time", data=build_time)
        info.create_dataset("scores", data=model.scores().T.astype(np.float32))
        mb = info.create_group("modelBuilder-0")
        mb.create_dataset("builderName", data=f"SSM Builder {__version__} (PCA via Gram matrix, paper eq. 4-6)")
        mb.create_dataset("buildTime", data=build_time)
        par = mb.create_group("parameters")
        for key in ("alignment", "ddof", "n_modes", "total_variance_mm2", "eigensolver"):
            if key in model.params and model.params[key] is not None:
                par.create_dataset(key, data=model.params[key])
        par.create_dataset("NoiseVariance", data=np.float32(noise_variance))
        dinfo = mb.create_group("dataInfo")
        for i, name in enumerate(model.instance_names):
            dinfo.create_dataset(f"URI_{i}", data=str(name))
        extra = f.create_group("ssm")
        extra.create_dataset("instance_names", data=np.asarray(model.instance_names, dtype=object), dtype=h5py.string_dtype())
        extra.create_dataset("instance_points", data=np.asarray(model.instance_points, dtype=float))
        extra.create_dataset("instance_points_world", data=np.asarray(model.instance_points_world, dtype=float))
        extra.create_dataset("params_json", data=json.dumps(jsonable(model.params)))
        if model.structure_names:  # a joint model: one reference of disconnected parts, and which part is which
            st = extra.create_group("structures")
            st.create_dataset("names", data=np.asarray(model.structure_names, dtype=object), dtype=h5py.string_dtype())
            st.create_dataset("offsets", data=np.asarray(model.structure_offsets, dtype=np.int64))
    return path


def load_statismo(path) -> ShapeModel:
    """Read a statismo HDF5 shape model (0.9 orthonormal basis, or 0.8 scaled basis).

    Mean, basis and variances are float32 in the format. Instance data come from the
    ``/ssm`` group when the file was written by SSM Builder (else they are empty).
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: statismo file not found")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise InputError(f"{path}: not an HDF5 file ({err})") from err
    with f:
        for key in ("model/mean", "model/pcaBasis", "model/pcaVariance", "representer/points"):
            if key not in f:
                raise InputError(f"{path}: not a statismo model, missing '/{key}'")
        major = int(f["version/majorVersion"][()]) if "version/majorVersion" in f else 0
        minor = int(f["version/minorVersion"][()]) if "version/minorVersion" in f else 8
        mean = np.asarray(f["model/mean"][()], dtype=float).reshape(-1, 3)
        basis = np.asarray(f["model/pcaBasis"][()], dtype=float)
        variances = np.asarray(f["model/pcaVariance"][()], dtype=float).reshape(-1)
        if basis.shape != (mean.size, variances.size):
            raise InputError(f"{path}: '/model/pcaBasis' has shape {basis.shape}; expected ({mean.size}, {variances.size})")
        if (major, minor) == (0, 8):
            sd = np.sqrt(variances)
            basis = basis / np.where(sd > 1e-8, sd, np.inf)[None]
        elif (major, minor) not in ((0, 9),) and major != 1:
            raise InputError(f"{path}: unsupported statismo version {major}.{minor}")
        cells = np.asarray(f["representer/cells"][()]) if "representer/cells" in f else np.zeros((3, 0), int)
        if cells.ndim != 2 or cells.shape[0] != 3:
            raise InputError(f"{path}: '/representer/cells' has shape {cells.shape}; expected (3, F) triangles")
        ssm_keys = ("instance_names", "instance_points", "instance_points_world", "params_json")
        if "ssm" in f and all(f"ssm/{k}" in f for k in ssm_keys):
            try:
                names = np.asarray([s.decode() if isinstance(s, bytes) else str(s)
                                    for s in f["ssm/instance_names"][()]])
                pts = np.asarray(f["ssm/instance_points"][()], dtype=float)
                world = np.asarray(f["ssm/instance_points_world"][()], dtype=float)
                pj = f["ssm/params_json"][()]
                params = json.loads(pj.decode() if isinstance(pj, bytes) else str(pj))
                structure_arrays = {}
                if "ssm/structures/names" in f and "ssm/structures/offsets" in f:
                    structure_arrays = {
                        "structure_names": np.asarray([s.decode() if isinstance(s, bytes) else str(s)
                                                       for s in f["ssm/structures/names"][()]]),
                        "structure_offsets": np.asarray(f["ssm/structures/offsets"][()])}
            except (ValueError, TypeError, UnicodeDecodeError) as err:
                raise InputError(f"{path}: the /ssm group is damaged ({type(err).__name__}: {err})") from None
            if not isinstance(params, dict):
                raise InputError(f"{path}: '/ssm/params_json' is not a JSON object")
        elif "ssm" in f:
            missing = [k for k in ssm_keys if f"ssm/{k}" not in f]
            raise InputError(f"{path}: the /ssm group (SSM Builder's training data) lacks {', '.join(missing)}; the "
                             "file is damaged or was edited (delete /ssm to use the model without its instances)")
        else:
            npts = mean.shape[0]
            names = np.zeros(0, dtype="<U1")
            pts = np.zeros((0, npts, 3))
            world = np.zeros((0, npts, 3))
            params = {"source": str(path), "total_variance_mm2": float(variances.sum())}
            structure_arrays = {}
    k = variances.size
    return model_from_arrays(
        {
            "mean": mean,
            "faces": cells.T.astype(np.int64),
            "modes": basis.T.reshape(k, -1, 3),
            "variances": variances,
            "instance_names": names,
            "instance_points": pts,
            "instance_points_world": world,
            "params": params,
            **structure_arrays,
        },
        str(path),
    )


def write_score_tables(model: ShapeModel, out_dir) -> dict:
    """``scores.csv`` and ``eigenvalues.csv`` in ``out_dir``: the tables the next tool reads.

    ``scores.csv``: one row per training instance, its mode weights b_k = q_kᵀ (p − p̄)
    (paper eq. 7) in standard deviations (``z1`` …, b_k / √λ_k) and in mm (``b1_mm`` …).
    ``eigenvalues.csv``: per mode its variance λ_k (mm²), σ_k = √λ_k (mm), its share of
    the total variance and the cumulative share (eq. 8).

    Returns ``{"scores": path, "eigenvalues": path}``.
    """
    out_dir = Path(out_dir)
    k = model.n_modes
    sd = np.sqrt(np.maximum(np.asarray(model.variances, float), 1e-300))
    b = model.project_all(model.instance_points).reshape(-1, k)
    with open(out_dir / "scores.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["instance"] + [f"z{i + 1}" for i in range(k)] + [f"b{i + 1}_mm" for i in range(k)])
        for name, row in zip(model.instance_names, b):
            w.writerow([str(name)] + [f"{x:.6g}" for x in row / sd] + [f"{x:.6g}" for x in row])
    share = np.asarray(model.variances, float) / max(float(model.total_variance), 1e-300)
    with open(out_dir / "eigenvalues.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["mode", "variance_mm2", "sd_mm", "fraction", "cumulative"])
        for i in range(k):
            w.writerow([i + 1, f"{model.variances[i]:.9g}", f"{sd[i]:.9g}", f"{share[i]:.6g}",
                        f"{share[: i + 1].sum():.6g}"])
    return {"scores": str(out_dir / "scores.csv"), "eigenvalues": str(out_dir / "eigenvalues.csv")}


def write_exchange_meshes(model: ShapeModel, out_dir, *, gltf: bool = True, vtk: bool = True, modes: int = 5,
                          sigmas: float = 2.0) -> dict:
    """The model as meshes other tools open (model frame; glTF in metres, VTK in mm).

    ``model.glb``: the mean shape with one morph target per mode (the first ``modes``),
    each +1 SD (√λ_k q_k), named ``Mode k (+1 SD)``. ``vtk/mean.vtp`` (and legacy
    ``vtk/mean.vtk``): the mean with the per-point variance (mm²) and the first mode's
    displacement; ``vtk/mode_<k>_minus<s>sd.vtp`` / ``_plus<s>sd.vtp``: the mean ∓ ``sigmas``
    SD along each of the first ``modes`` modes, as ShapeWorks' analysis writes them. A joint
    model: ``model.glb`` holds one primitive per structure sharing the mesh's morph weights,
    and ``vtk/<structure>/`` the same set for each structure's rows.
    Returns ``{name: path}``.
    """
    out_dir = Path(out_dir)
    k = min(int(modes), model.n_modes)
    sd = model.standard_deviations
    written = {}
    if gltf:
        targets = {f"Mode {i + 1} (+1 SD)": sd[i] * model.modes[i] for i in range(k)}
        parts = {n: model.structure_slice(n) for n in model.structure_names} or None
        written["gltf"] = str(write_glb(out_dir / "model.glb", model.mean, model.faces, targets, parts=parts,
                                        display_turn=display_axes(model)))
    if vtk:
        folder = out_dir / "vtk"
        _write_vtk_set(folder, model.mean, model.faces, model.point_variance, sd[:k], model.modes[:k], sigmas)
        for name in model.structure_names:  # a joint model: each structure's own set besides
            sl = model.structure_slice(name)
            _write_vtk_set(folder / str(name), model.mean[sl], model.structure_faces(name), model.point_variance[sl],
                           sd[:k], model.modes[:k, sl], sigmas)
        written["vtk"] = str(folder)
    return written


def _write_vtk_set(folder: Path, mean, faces, variance, sd, modes, sigmas: float) -> None:
    """``mean.vtp``/``mean.vtk`` and the ∓ ``sigmas`` SD shapes of each mode into ``folder``."""
    folder.mkdir(exist_ok=True)
    fields = {"variance_mm2": variance}
    if len(sd):
        fields["mode_1_sd_mm"] = sd[0] * modes[0]
    write_vtp(folder / "mean.vtp", mean, faces, fields)
    write_vtk(folder / "mean.vtk", mean, faces, fields, title="SSM Builder mean shape (mm)")
    tag = f"{sigmas:g}".replace(".", "p")
    for i in range(len(sd)):
        for sign, word in ((-1, "minus"), (1, "plus")):
            shift = sign * sigmas * sd[i] * modes[i]
            write_vtp(folder / f"mode_{i + 1}_{word}{tag}sd.vtp", mean + shift, faces, {"displacement_mm": shift})


def write_model_files(model: ShapeModel, out_dir, *, statismo: bool = True, statismo_name: str = "model.h5",
                      tables: bool = True, gltf: bool = False, vtk: bool = False, exchange_modes: int = 5,
                      npz_extra: dict | None = None) -> dict:
    """Write ``model.npz``, (``statismo``) the statismo file, (``tables``) the score tables
    (:func:`write_score_tables`) and (``gltf``, ``vtk``) the exchange meshes
    (:func:`write_exchange_meshes`) into ``out_dir``.

    Returns ``{"npz": path, "statismo": path, "scores": path, "eigenvalues": path, "gltf": path,
    "vtk": folder}`` (only what was written).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {"npz": str(save_npz(model, out_dir / "model.npz", extra=npz_extra))}
    if statismo:
        written["statismo"] = str(save_statismo(model, out_dir / statismo_name))
    if tables and model.n_instances:
        written.update(write_score_tables(model, out_dir))
    if gltf or vtk:
        written.update(write_exchange_meshes(model, out_dir, gltf=gltf, vtk=vtk, modes=exchange_modes))
    return written


def model_file(path) -> Path:
    """The model file ``path`` names: the file itself, or the ``model.npz`` inside a build's output
    folder. An InputError names a folder without one and a path that does not exist."""
    path = Path(path).expanduser()
    if path.is_dir():
        inside = path / "model.npz"
        if inside.is_file():
            return inside
        raise InputError(f"{path}: is a folder without a model.npz (give a build's output folder or a model file: "
                         "model.npz or a statismo .h5)")
    if not path.is_file():
        raise InputError(f"{path}: model file not found")
    return path


def load_model(path, *, say=None):
    """A model from ``model.npz`` (or a build's output folder holding one) or a statismo HDF5 file
    (ours or another tool's), without its
    modes of zero variance (:func:`~ssm_addon.model.pca.drop_empty_modes`: another tool may
    keep n − 1 or more modes of which many are empty); a statismo file whose reference is
    several disconnected parts, each a contiguous range of points, opens as a joint model of its
    parts (:func:`~ssm_addon.model.joint.joined_parts`). ``say`` receives the lines saying so."""
    path = model_file(path)
    head = path.read_bytes()[:8]
    if head.startswith(b"PK"):
        model = load_npz(path)
    elif head.startswith(b"\x89HDF"):
        model = load_statismo(path)
        joined = joined_parts(model)  # another tool's joined model: its parts as structures
        if joined is not None:
            model = joined
            if say is not None:
                say(f"{path.name}: its reference is {len(joined.structure_names)} disconnected parts, each a "
                    "contiguous range of points (several structures joined into one model): opened as a joint "
                    f"model of {', '.join(joined.structure_names)}")
    else:
        raise InputError(f"{path}: not a model (expected model.npz from `ssm build` or a statismo .h5 file)")
    model, dropped = drop_empty_modes(model)
    if dropped and say is not None:
        say(f"{path.name}: {dropped} of {model.n_modes + dropped} modes have zero variance (at most "
            f"{EMPTY_MODE_SHARE:g} of the largest); dropped, {model.n_modes} modes left")
    return model
