"""Label maps in and out: NIfTI, NRRD/NHDR, MetaImage, NumPy (paper section 2's input).

*World* coordinates are the file's scanner/patient coordinates in mm, RAS: NRRD and
MetaImage LPS spaces are converted to RAS on load. Every reader returns a
:class:`LabelMap` (integer labels and the voxel -> world affine).
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np

from ..base.errors import InputError
from .grid import AffineGrid
from .meshes import MESH_EXTENSIONS
from .registry import extensions, format_of, registered_extension


@dataclass(frozen=True)
class LabelMap(AffineGrid):
    """A label map as read from disk (an :class:`~.grid.AffineGrid` of its labels).

    Attributes
    ----------
    labels : (I, J, K) integer ndarray
        Label per voxel (0 = background).
    affine : (4, 4) float ndarray
        Voxel index (i, j, k, 1) -> world (x, y, z, 1) in mm (RAS).
    path : str
        The file it came from (for messages).
    """

    labels: np.ndarray
    affine: np.ndarray
    path: str = ""

    GRID_ARRAY = "labels"


@dataclass(frozen=True)
class Volume(AffineGrid):
    """A binary object in its input grid (an :class:`~.grid.AffineGrid` of its mask).

    Attributes
    ----------
    mask : (I, J, K) bool ndarray
        True inside the object.
    affine : (4, 4) float ndarray
        Voxel index -> world mm.
    source : str
        File or object the mask came from.
    label : int or None
        The label picked from a label map (None: all non-zero, or a mesh).
    patient_oriented : bool
        True when world axes are patient axes (R, A, S), i.e. the input was an image
        with an orientation; False for meshes in arbitrary coordinates.
    """

    mask: np.ndarray
    affine: np.ndarray
    source: str = ""
    label: int | None = None
    patient_oriented: bool = True

    GRID_ARRAY = "mask"

    @property
    def volume_mm3(self) -> float:
        """Object volume in mm³: voxel count × voxel volume."""
        return float(np.count_nonzero(self.mask)) * self.voxel_volume_mm3



IMAGE_EXTENSIONS = extensions("label map")
SUPPORTED_EXTENSIONS = IMAGE_EXTENSIONS + MESH_EXTENSIONS

_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def file_extension(path) -> str:
    """The lower-case extension of ``path`` including ``.nii.gz``-style double suffixes
    (:func:`~.registry.registered_extension`)."""
    return registered_extension(path)


def file_stem(path) -> str:
    """The file name without its (possibly double) extension."""
    name = Path(path).name
    ext = file_extension(path)
    return name[: len(name) - len(ext)] if ext else name


def is_mesh_file(path) -> bool:
    """True for the surface mesh formats (STL, PLY, OBJ)."""
    return file_extension(path) in MESH_EXTENSIONS


def _check_file(path, kinds: tuple[str, ...]) -> tuple[Path, str]:
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a file; give the file inside it ({', '.join(kinds)})")
    ext = file_extension(path)
    if ext not in kinds:
        raise InputError(f"{path}: unknown file extension {ext or '(none)'!r}; supported: {', '.join(kinds)}")
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    return path, ext


MAX_DISTINCT_LABELS = 1000
"""A label map with more distinct values than this is taken for an intensity image."""


def _refuse_intensities(data: np.ndarray, path) -> None:
    """Refuse images that look like intensities (CT, MR) rather than labels.

    Labels are few distinct whole numbers (TotalSegmentator: ~120); a CT has thousands
    of values, an interpolated map fractional ones. Checked on at most ~1 million voxels
    sampled evenly (O(n) counting), a few milliseconds on any image.
    """
    if data.dtype.kind in "iub" and data.dtype.itemsize == 1:
        return  # at most 256 distinct values: nothing to count
    flat = data.reshape(-1)
    sample = np.ascontiguousarray(flat[:: max(1, flat.size // 500_000)])
    whole = sample  # integer labels are whole already (rounding them went through float)
    if data.dtype.kind == "f":
        whole = np.rint(sample)
        frac = np.abs(sample - whole)
        bad = np.count_nonzero(frac > 1e-3)
        if bad > 0.001 * sample.size:
            raise InputError(f"{path}: looks like an intensity image, not a label map: {100 * bad / sample.size:.1f} % "
                             f"of the voxels hold fractional values (e.g. {float(sample[np.argmax(frac)]):g}); give the "
                             "segmentation (whole-number labels, 0 = background)")
    lo, hi = float(whole.min()), float(whole.max())
    if hi - lo < 1 << 20:  # whole numbers in a modest range: count them in O(n)
        distinct = int(np.count_nonzero(np.bincount((whole - lo).astype(np.int64))))
    else:
        distinct = int(np.unique(sample).size)
    if distinct > MAX_DISTINCT_LABELS:
        raise InputError(f"{path}: looks like an intensity image, not a label map: {distinct:,} distinct values "
                         f"from {lo:g} to {hi:g} (a label map has a few labels, 0 = background; more than "
                         f"{MAX_DISTINCT_LABELS} are refused); give the segmentation")


def _as_labels(data: np.ndarray, path) -> np.ndarray:
    """3-D integer labels from a raw image array (4-D with a singleton 4th axis is squeezed).

    Float-stored labels (common: VerSe stores float64) are rounded to the nearest integer
    and cast to the smallest integer type that holds them.
    """
    data = np.asanyarray(data)
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim == 4:
        raise InputError(
            f"{path}: 4-D image of shape {tuple(data.shape)}; a label map must be 3-D "
            "(one volume, not a time series or multi-channel image)"
        )
    if data.ndim != 3:
        raise InputError(f"{path}: {data.ndim}-D image of shape {tuple(data.shape)}; a label map must be 3-D")
    if data.dtype == bool:
        return data.astype(np.uint8)
    if data.dtype.kind not in "iuf":
        raise InputError(f"{path}: unsupported voxel type {data.dtype}; expected integer or float labels")
    if data.dtype.kind == "f" and not np.isfinite(data).all():
        raise InputError(f"{path}: the label map contains NaN or infinite values")
    _refuse_intensities(data, path)
    if data.dtype.kind in "iu":
        return data
    lo, hi = float(data.min()), float(data.max())
    dtype = np.result_type(np.min_scalar_type(int(round(lo))), np.min_scalar_type(int(round(hi))))
    return np.rint(data).astype(dtype)


def _read_nifti(path: Path):

    img = nib.load(str(path))
    with nib.openers.ImageOpener(str(path)) as f:  # the header as written (nibabel mends zero voxel sizes to 1)
        hdr = type(img.header).from_fileobj(f, check=False)
    if hasattr(hdr, "get_qform") and int(hdr["qform_code"]) == 0 and int(hdr["sform_code"]) == 0:
        zooms = np.asarray(hdr["pixdim"][1:4], dtype=float)  # the affine comes from these alone
        bad = [i + 1 for i, z in enumerate(zooms) if not (np.isfinite(z) and z > 0)]
        if bad:
            raise InputError(f"{path}: the header gives voxel size {zooms.tolist()} (pixdim {bad[0]} is not a "
                             "positive number) and no orientation (qform and sform codes 0): the voxels have no size "
                             "in mm; fix the header (e.g. resave it from the segmentation tool)")
    data = np.asanyarray(img.dataobj)
    affine, _note = nifti_affine(img.header)
    return data, affine


def label_map_coordinates(path) -> str:
    """How a label map's world coordinates are taken (read from its header alone), for the report."""
    path = Path(path)
    ext = file_extension(path)
    try:
        if ext in (".nii", ".nii.gz"):
            return nifti_affine(nib.load(str(path)).header)[1]
        if ext in (".nrrd", ".nhdr"):
            space = str(nrrd.read_header(str(path)).get("space", "none stated: taken as RAS"))
            return f"NRRD space {space}" + (", turned into RAS" if _anatomical_signs(space) is not None
                                            and space.lower() not in ("ras", "right-anterior-superior") else "")
        if ext in (".mha", ".mhd"):
            return "MetaImage (LPS, as ITK writes it), turned into RAS"
    except (OSError, ValueError, InputError) as err:
        return f"header not read ({err})"
    return "NumPy array: the spacing and affine given with it (RAS)"


#: qform and sform that differ by less than this (mm, at the corners of a 100-voxel cube) are one transform.
NIFTI_FORM_TOLERANCE_MM = 1e-3


def nifti_affine(header) -> tuple[np.ndarray, str]:
    """The voxel -> world (RAS mm) affine of a NIfTI header as 3D Slicer (ITK) reads it, and a note.

    Both forms set: the sform when its code is 1 (scanner) or when it equals the qform,
    else the qform (the scanner's: an sform coded 'aligned', 'Talairach' or 'MNI' maps to
    another space). One set: that one. Neither: the voxel sizes alone. nibabel (and FSL)
    take the sform whenever its code is set, so a file whose forms differ lands elsewhere
    there: the note says which form was used and by how much they differ.
    """
    q_code, s_code = int(header["qform_code"]), int(header["sform_code"])
    qform = np.asarray(header.get_qform(), float) if q_code > 0 else None
    sform = np.asarray(header.get_sform(), float) if s_code > 0 else None
    if qform is None and sform is None:
        return np.asarray(header.get_best_affine(), float), "NIfTI without qform or sform: voxel sizes only"
    if qform is None:
        return sform, f"NIfTI sform (code {s_code})"
    if sform is None:
        return qform, f"NIfTI qform (code {q_code})"
    corners = np.array([[i, j, k, 1.0] for i in (0, 100) for j in (0, 100) for k in (0, 100)])
    differ = float(np.abs(corners @ (sform - qform).T)[:, :3].max())
    if differ <= NIFTI_FORM_TOLERANCE_MM:
        return sform, "NIfTI sform (equal to its qform)"
    if s_code == 1:
        return sform, (f"NIfTI sform (code 1, scanner), as 3D Slicer reads it; its qform differs by up to "
                       f"{differ:.3g} mm")
    return qform, (f"NIfTI qform, as 3D Slicer reads it: the sform (code {s_code}, not the scanner's) differs by up "
                   f"to {differ:.3g} mm (nibabel and FSL would use the sform)")


def _anatomical_signs(space: str) -> np.ndarray | None:
    """(3,) signs that turn a NRRD ``space`` into RAS, or None if it is not anatomical."""
    space = space.strip().lower()
    short = {"ras": "right-anterior-superior", "las": "left-anterior-superior", "lps": "left-posterior-superior"}
    space = short.get(space, space)
    words = space.split("-")
    if len(words) != 3:
        return None
    table = {"right": 1.0, "left": -1.0, "anterior": 1.0, "posterior": -1.0, "superior": 1.0, "inferior": -1.0}
    if any(w not in table for w in words):
        return None
    return np.array([table[w] for w in words])


def _read_nrrd(path: Path):

    data, header = nrrd.read(str(path))
    ndim = data.ndim
    affine = np.eye(4)
    directions = header.get("space directions")
    if directions is not None:
        rows = []
        for axis, row in enumerate(directions):
            row = np.asarray(row, dtype=float) if row is not None else np.full(3, np.nan)
            if row.size == 3 and np.all(np.isfinite(row)):
                rows.append((axis, row))
        if len(rows) != 3:
            if ndim == 4 and data.shape[-1] == 1:
                rows = rows[:3]
            else:
                raise InputError(f"{path}: {ndim}-D image of shape {data.shape}; a label map must be 3-D")
        spatial = [axis for axis, _ in rows]
        if ndim == 4:
            nonspatial = [a for a in range(4) if a not in spatial]
            if data.shape[nonspatial[0]] != 1:
                raise InputError(
                    f"{path}: 4-D image of shape {data.shape}; a label map must be 3-D "
                    "(one volume, not a time series or multi-channel image)"
                )
            data = np.squeeze(data, axis=nonspatial[0])
        for col, (_, row) in enumerate(rows):
            affine[:3, col] = row
    elif "spacings" in header:
        sp = np.asarray(header["spacings"], dtype=float)[:3]
        if not np.all(np.isfinite(sp) & (sp > 0)):
            raise InputError(f"{path}: 'spacings' {sp.tolist()} are not all positive numbers: the voxels have no size "
                             "in mm")
        affine[:3, :3] = np.diag(sp)
    else:
        raise InputError(f"{path}: the NRRD header has neither 'space directions' nor 'spacings': the voxel size and "
                         "orientation are unknown, and a model needs mm in the image's world (resave it from "
                         "3D Slicer, or add 'space: left-posterior-superior' and 'space directions')")
    origin = header.get("space origin")
    if origin is not None:
        affine[:3, 3] = np.asarray(origin, dtype=float)[:3]
    signs = _anatomical_signs(str(header.get("space", "right-anterior-superior")))
    if signs is not None:
        affine = np.diag(np.append(signs, 1.0)) @ affine
    return data, affine


_MET_TYPES = {
    "MET_CHAR": "i1",
    "MET_UCHAR": "u1",
    "MET_SHORT": "i2",
    "MET_USHORT": "u2",
    "MET_INT": "i4",
    "MET_UINT": "u4",
    "MET_LONG": "i4",
    "MET_ULONG": "u4",
    "MET_LONG_LONG": "i8",
    "MET_ULONG_LONG": "u8",
    "MET_FLOAT": "f4",
    "MET_DOUBLE": "f8",
}


def _read_metaimage_header(raw: bytes, path) -> tuple[dict[str, str], int]:
    """Parse ``Key = Value`` lines up to ``ElementDataFile``; return (header, data offset)."""
    header: dict[str, str] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            if "elementdatafile" not in header and pos < len(raw):
                end = len(raw)
            else:
                break
        line = raw[pos:end].decode("latin-1").strip()
        pos = end + 1
        if not line:
            continue
        if "=" not in line:
            raise InputError(f"{path}: corrupt MetaImage header line {line[:60]!r} (expected 'Key = Value')")
        key, value = line.split("=", 1)
        header[key.strip().lower()] = value.strip()
        if key.strip().lower() == "elementdatafile":
            break
        if pos > 1 << 20:
            break
    if "elementdatafile" not in header:
        raise InputError(f"{path}: corrupt MetaImage header: no ElementDataFile entry")
    return header, pos


def _floats(header, key, n, default, path):
    if key not in header:
        return np.asarray(default, dtype=float)
    try:
        values = np.array([float(x) for x in header[key].split()], dtype=float)
    except ValueError as err:
        raise InputError(f"{path}: corrupt MetaImage header field {key}: {header[key]!r}") from err
    if values.size < n:
        raise InputError(f"{path}: MetaImage field {key} has {values.size} values, expected {n}")
    return values


def _read_metaimage(path: Path):
    """A MetaImage (.mha / .mhd) reader: header keys of ITK's MetaIO, world LPS -> RAS."""
    raw = path.read_bytes()
    header, offset = _read_metaimage_header(raw, path)
    if header.get("objecttype", "Image").lower() != "image":
        raise InputError(f"{path}: MetaImage ObjectType {header['objecttype']!r} is not an image")
    try:
        ndims = int(header.get("ndims", "0"))
        dims = [int(x) for x in header.get("dimsize", "").split()]
    except ValueError as err:
        raise InputError(f"{path}: corrupt MetaImage header (NDims/DimSize)") from err
    if ndims == 0 or len(dims) != ndims:
        raise InputError(f"{path}: corrupt MetaImage header: NDims={ndims}, DimSize={dims}")
    channels = int(header.get("elementnumberofchannels", "1"))
    if channels != 1:
        raise InputError(f"{path}: 4-D image ({channels} channels per voxel); a label map must be 3-D")
    if ndims == 4 and dims[3] == 1:
        pass
    elif ndims == 4:
        raise InputError(
            f"{path}: 4-D image of shape {tuple(dims)}; a label map must be 3-D "
            "(one volume, not a time series or multi-channel image)"
        )
    elif ndims != 3:
        raise InputError(f"{path}: {ndims}-D image of shape {tuple(dims)}; a label map must be 3-D")
    etype = header.get("elementtype", "").upper()
    if etype not in _MET_TYPES:
        raise InputError(f"{path}: unsupported MetaImage ElementType {etype!r}")
    msb = (header.get("binarydatabyteordermsb") or header.get("elementbyteordermsb") or "False").lower() == "true"
    dtype = np.dtype(_MET_TYPES[etype]).newbyteorder(">" if msb else "<")
    count = int(np.prod(dims))
    datafile = header["elementdatafile"]
    if datafile.upper() == "LOCAL":
        payload = raw[offset:]
    else:
        if datafile.upper().startswith("LIST") or "%" in datafile:
            raise InputError(f"{path}: MetaImage ElementDataFile {datafile!r} (file lists) is not supported")
        data_path = path.parent / datafile
        if not data_path.is_file():
            raise InputError(f"{path}: MetaImage data file {data_path} not found")
        payload = data_path.read_bytes()
        skip = int(header.get("headersize", "0"))
        if skip == -1:
            payload = payload[len(payload) - count * dtype.itemsize :]
        elif skip > 0:
            payload = payload[skip:]
    if header.get("compresseddata", "False").lower() == "true":
        try:
            payload = zlib.decompress(payload, zlib.MAX_WBITS | 32)
        except zlib.error as err:
            raise InputError(f"{path}: corrupt or truncated compressed MetaImage data ({err})") from err
    if len(payload) < count * dtype.itemsize:
        raise InputError(
            f"{path}: truncated MetaImage data: expected {count * dtype.itemsize} bytes, found {len(payload)}"
        )
    data = np.frombuffer(payload, dtype=dtype, count=count).reshape(dims[::-1]).T
    if ndims == 4:
        data = data[..., 0]
    spacing = _floats(header, "elementspacing", 3, np.ones(3), path)
    if "elementspacing" not in header and "elementsize" in header:
        spacing = _floats(header, "elementsize", 3, np.ones(3), path)
    origin = np.zeros(3)
    for key in ("offset", "position", "origin"):
        if key in header:
            origin = _floats(header, key, 3, origin, path)
            break
    direction = np.eye(ndims).ravel()
    for key in ("transformmatrix", "rotation", "orientation"):
        if key in header:
            direction = _floats(header, key, ndims * ndims, direction, path)
            break
    direction = direction[: ndims * ndims].reshape(ndims, ndims)[:3, :3]
    affine = np.eye(4)
    # MetaIO stores one row per image axis: row i is axis i's direction (ITK: SetDirection(i, row)).
    affine[:3, :3] = direction.T * spacing[:3]
    affine[:3, 3] = origin[:3]
    return data, _LPS_TO_RAS @ affine


def _spacing_affine(spacing, path) -> np.ndarray:
    sp = np.broadcast_to(np.asarray(spacing, dtype=float).ravel(), (3,)) if np.size(spacing) in (1, 3) else None
    if sp is None or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise InputError(f"{path}: spacing must be one or three positive numbers (mm), got {spacing!r}")
    return np.diag(np.append(sp, 1.0))


def _numpy_geometry(path: Path, spacing_mm, affine, sidecar: dict | None):
    if affine is not None:
        a = np.asarray(affine, dtype=float)
        if a.shape != (4, 4) or not np.all(np.isfinite(a)) or abs(np.linalg.det(a[:3, :3])) < 1e-12:
            raise InputError(f"{path}: the affine must be a finite, invertible 4x4 matrix (voxel -> world mm)")
        return a
    if spacing_mm is not None:
        return _spacing_affine(spacing_mm, path)
    if sidecar is not None:
        if "affine" in sidecar:
            return _numpy_geometry(path, None, sidecar["affine"], None)
        for key in ("spacing_mm", "spacing"):
            if key in sidecar:
                return _spacing_affine(sidecar[key], path)
    raise InputError(
        f"{path}: a NumPy array has no voxel size; pass spacing_mm, store 'spacing' or 'affine' in an .npz, "
        f'or write a sidecar {path.with_suffix(".json").name} with {{"spacing_mm": [sx, sy, sz]}}'
    )


def _read_numpy(path: Path, ext: str, spacing_mm=None):

    sidecar = None
    side = path.with_suffix(".json")
    if side.is_file():
        try:
            sidecar = json.loads(side.read_text())
        except ValueError as err:
            raise InputError(f"{side}: not valid JSON ({err})") from err
    if ext == ".npy":
        data = np.load(path, allow_pickle=False)
        return data, _numpy_geometry(path, spacing_mm, None, sidecar)
    with np.load(path, allow_pickle=False) as npz:
        if "labels" not in npz.files:
            raise InputError(f"{path}: no array 'labels' in the .npz (found: {', '.join(npz.files) or 'none'})")
        data = npz["labels"]
        affine = npz["affine"] if "affine" in npz.files else None
        spacing = npz["spacing"] if "spacing" in npz.files else spacing_mm
    return data, _numpy_geometry(path, spacing, affine, sidecar)


#: The reader of each image format of :mod:`.registry` (NumPy arrays read apart: they need a spacing).
_IMAGE_READERS = {"NIfTI": _read_nifti, "NRRD": _read_nrrd, "MetaImage": _read_metaimage}


def read_label_map(path, spacing_mm=None) -> LabelMap:
    """Read a label map and its voxel -> world (RAS, mm) affine.

    Formats: NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr; LPS/LAS spaces -> RAS),
    MetaImage (.mha, .mhd; world LPS -> RAS, as ITK writes it), NumPy (.npy with
    ``spacing_mm`` or a sidecar ``<name>.json`` holding ``spacing_mm`` or ``affine``;
    .npz with arrays ``labels`` and ``affine`` (4x4) or ``spacing``). Oblique directions
    and anisotropic spacing are kept in the affine. Float-stored labels are rounded.

    Parameters
    ----------
    path : str or Path
        The label map file.
    spacing_mm : float or (3,) floats, optional
        Voxel size for a bare .npy array (mm).

    Returns
    -------
    LabelMap
        Integer labels (I, J, K) and the (4, 4) affine voxel -> world mm (RAS).

    Raises
    ------
    InputError
        Missing file, unknown extension, unreadable/corrupt/truncated file, a 4-D image.
    """
    path, ext = _check_file(path, IMAGE_EXTENSIONS)
    kind = format_of(path, "label map").name
    try:
        if kind == "NumPy":
            data, affine = _read_numpy(path, ext, spacing_mm)
        else:
            data, affine = _IMAGE_READERS[kind](path)
        labels = _as_labels(data, path)
    except InputError:
        raise
    except MemoryError:
        raise
    except Exception as err:  # noqa: BLE001 - every reader failure becomes a named InputError
        raise InputError(
            f"{path}: cannot read {kind} file, corrupt or truncated? ({type(err).__name__}: {err})"
        ) from err
    affine = np.asarray(affine, dtype=float)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise InputError(f"{path}: degenerate voxel -> world affine {affine.tolist()}")
    return LabelMap(labels=labels, affine=affine, path=str(path))


GREY_IMAGE_EXTENSIONS = extensions("image")


def read_image_array(path) -> tuple[np.ndarray, np.ndarray, Path]:
    """The voxel array of any image (grey values kept as stored) and its voxel -> world RAS mm
    affine, read as :func:`read_label_map` reads them (NIfTI, NRRD, MetaImage).

    Raises
    ------
    InputError
        Missing, unknown, unreadable or truncated file, or a degenerate affine.
    """
    path, _ext = _check_file(path, GREY_IMAGE_EXTENSIONS)
    try:
        data, affine = _IMAGE_READERS[format_of(path, "image").name](path)
        data = np.asarray(data)
    except InputError:
        raise
    except MemoryError:
        raise
    except Exception as err:  # noqa: BLE001 - every reader failure becomes a named InputError
        raise InputError(f"{path}: cannot read the image, corrupt or truncated? ({type(err).__name__}: {err})") from err
    affine = np.asarray(affine, dtype=float)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise InputError(f"{path}: degenerate voxel -> world affine {affine.tolist()}")
    return data, affine, path


def write_label_map(path, labels: np.ndarray, affine: np.ndarray, compress: bool = True) -> Path:
    """Write a label map with its affine (voxel -> world RAS mm) in the format of ``path``.

    NIfTI, NRRD (stored as LPS, as 3D Slicer does), MetaImage (.mha with local data,
    .mhd with a .raw file; LPS) and .npz (``labels`` + ``affine``). Used by the tests and
    the demo; :func:`read_label_map` reads each back to the same labels and affine.
    """
    path = Path(path)
    ext = file_extension(path)
    labels = np.asarray(labels)
    affine = np.asarray(affine, dtype=float)
    if ext in (".nii", ".nii.gz"):

        if labels.dtype in (np.int64, np.uint64):
            labels = labels.astype(np.int32)
        elif labels.dtype == bool:
            labels = labels.astype(np.uint8)
        img = nib.Nifti1Image(labels, affine)
        img.set_qform(affine, code=1)
        img.set_sform(affine, code=1)
        nib.save(img, str(path))
    elif ext in (".nrrd", ".nhdr"):

        lps = _LPS_TO_RAS @ affine
        header = {
            "space": "left-posterior-superior",
            "space directions": lps[:3, :3].T,
            "space origin": lps[:3, 3],
            "kinds": ["domain", "domain", "domain"],
            "encoding": "gzip" if compress else "raw",
        }
        nrrd.write(str(path), labels, header, detached_header=ext == ".nhdr")
    elif ext in (".mha", ".mhd"):

        lps = _LPS_TO_RAS @ affine
        spacing = np.linalg.norm(lps[:3, :3], axis=0)
        directions = lps[:3, :3] / spacing
        rev = {v: k for k, v in _MET_TYPES.items() if k not in ("MET_LONG", "MET_ULONG")}
        code = np.dtype(labels.dtype).newbyteorder("=").str[1:]
        if code not in rev:
            labels = labels.astype(np.int32)
            code = "i4"
        payload = np.asarray(labels, dtype="<" + code).ravel(order="F").tobytes()
        if compress:
            payload = zlib.compress(payload)

        def fmt(values):
            return " ".join(repr(float(v)) for v in np.ravel(values))

        lines = [
            "ObjectType = Image",
            "NDims = 3",
            "BinaryData = True",
            "BinaryDataByteOrderMSB = False",
            f"CompressedData = {compress}",
        ]
        if compress:
            lines.append(f"CompressedDataSize = {len(payload)}")
        lines += [
            f"TransformMatrix = {fmt(directions.T)}",
            f"Offset = {fmt(lps[:3, 3])}",
            "CenterOfRotation = 0 0 0",
            "AnatomicalOrientation = RAI",
            f"ElementSpacing = {fmt(spacing)}",
            f"DimSize = {' '.join(str(int(s)) for s in labels.shape)}",
            f"ElementType = {rev[code]}",
        ]
        if ext == ".mha":
            lines.append("ElementDataFile = LOCAL")
            path.write_bytes(("\n".join(lines) + "\n").encode() + payload)
        else:
            raw = path.with_suffix(".zraw" if compress else ".raw")
            lines.append(f"ElementDataFile = {raw.name}")
            path.write_text("\n".join(lines) + "\n")
            raw.write_bytes(payload)
    elif ext == ".npz":
        np.savez_compressed(path, labels=labels, affine=affine)
    else:
        raise InputError(f"{path}: cannot write label maps as {ext!r}; use .nii(.gz), .nrrd, .mha, .mhd or .npz")
    return path


# ---------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------


def label_counts(label_map: LabelMap) -> dict[int, int]:
    """Voxel count of every non-zero label, ``{label: count}`` in ascending label order."""
    labels = label_map.labels
    flat = np.ravel(labels, order="K")
    if flat.size == 0:
        return {}
    lo = 0 if flat.dtype.kind in "ub" else int(flat.min())
    hi = int(flat.max())
    if lo >= 0 and hi < (1 << 22):
        counts = np.zeros(hi + 1, dtype=np.int64)
        step = 1 << 23
        for start in range(0, flat.size, step):
            counts += np.bincount(flat[start : start + step], minlength=hi + 1)
        values = np.nonzero(counts)[0]
        return {int(v): int(counts[v]) for v in values if v != 0}
    values, counts = np.unique(flat, return_counts=True)
    return {int(v): int(c) for v, c in zip(values, counts) if v != 0}


def _format_counts(counts: dict[int, int]) -> str:
    return ", ".join(f"{k} ({v} voxels)" for k, v in counts.items()) or "none"


def select_label(label_map: LabelMap, label: int | None = None) -> Volume:
    """Binary mask of one label (or of all non-zero labels when ``label`` is None).

    Raises
    ------
    InputError
        The label is not present (the message lists the labels present with their
        voxel counts) or the mask is empty.
    """
    labels = label_map.labels
    if label is None or int(label) < 0:
        mask = labels != 0
        if not mask.any():
            raise InputError(f"{label_map.path}: empty mask: the label map has no non-zero voxels")
        return Volume(mask=mask, affine=label_map.affine, source=label_map.path, label=None, patient_oriented=True)
    if int(label) == 0:
        raise InputError(
            f"{label_map.path}: label 0 is the background; pick a label from {_format_counts(label_counts(label_map))}"
        )
    mask = labels == int(label)
    if not mask.any():
        counts = label_counts(label_map)
        if not counts:
            raise InputError(f"{label_map.path}: empty mask: label {label} is not present and the map is empty")
        raise InputError(f"{label_map.path}: label {label} is not present; labels present: {_format_counts(counts)}")
    return Volume(mask=mask, affine=label_map.affine, source=label_map.path, label=int(label), patient_oriented=True)


def load_volume(path, label: int | None = None, spacing_mm=None) -> Volume:
    """Read a label map and pick one label (None: all non-zero), see :func:`read_label_map`."""
    return select_label(read_label_map(path, spacing_mm=spacing_mm), label)
