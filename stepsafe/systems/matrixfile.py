"""Matrix files of the ``system:`` key (``.npy``, ``.npz``, ``.mtx``), read within budgets.

Every file is checked from its header before anything is allocated: the file type (a
regular file, :func:`stepsafe.files.yamlio.open_regular`), its size (:data:`MAX_FILE_BYTES`), for
an ``.npz`` the declared unpacked size of its members (the same budget), the shape and the
type of the values. Refused, with a one-line :class:`~stepsafe.exceptions.StepsafeError`:

* values that are not real numbers: complex, booleans, text, Python objects, structured
  (record) or date/time dtypes, and Matrix Market ``complex`` or ``pattern`` (no values)
  files. Complex values are never truncated to their real part.
* anything that is not a square 2-D matrix (a 0-d scalar, a vector, a 3-D array);
* a dense matrix over :data:`MAX_DENSE_BYTES` as float64 (a 5000 x 5000 matrix);
* a sparse matrix larger than :data:`MAX_SPARSE_DIM` rows or with more than
  :data:`MAX_SPARSE_NNZ` stored entries (read from ``shape.npy``/``data.npy`` headers of a
  ``scipy.sparse.save_npz`` file or from the size line of an ``.mtx`` file).

Integer and float arrays of any width are accepted and converted to float64.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.files.yamlio import open_regular

if TYPE_CHECKING:  # pragma: no cover
    import zipfile

MAX_FILE_BYTES = 512 << 20  # a matrix file, and the declared unpacked size of an .npz
MAX_DENSE_BYTES = 200_000_000  # a dense matrix as float64: at most 5000 x 5000
MAX_SPARSE_DIM = 1_000_000  # rows (and columns) of a sparse matrix
MAX_SPARSE_NNZ = 10_000_000  # stored entries of a sparse matrix
MAX_NPZ_MEMBERS = 16  # arrays in one .npz (a sparse matrix saved by scipy has at most 6)

_SPARSE_FORMATS = ("csr", "csc", "coo", "bsr", "dia")
_MM_REAL_FIELDS = ("real", "double", "integer", "unsigned-integer")


def _refuse(label: str, message: str) -> StepsafeError:
    return StepsafeError(message, label)


def check_dtype(dtype: np.dtype, label: str) -> None:
    """Refuse every dtype that is not a real number (float or integer)."""
    kind = dtype.kind
    if dtype.fields is not None or dtype.subdtype is not None or kind == "V":
        raise _refuse(label, f"structured (record) values are not allowed, got dtype {dtype}; "
                             "save a plain array of real numbers")
    if kind == "c":
        raise _refuse(label, "complex values are not allowed: a stiffness, mass or Hessian "
                             "matrix is real (the real part is never taken silently)")
    if kind == "b":
        raise _refuse(label, "boolean values are not allowed; save real numbers")
    if kind in "US":
        raise _refuse(label, "text values are not allowed; save real numbers")
    if kind == "O":
        raise _refuse(label, "Python objects are not allowed; save real numbers")
    if kind in "mM":
        raise _refuse(label, "date/time values are not allowed; save real numbers")
    if kind not in "fiu":
        raise _refuse(label, f"values of dtype {dtype} are not allowed; save real numbers")


def _square(shape: tuple, label: str) -> int:
    if len(shape) == 0:
        raise _refuse(label, "holds a single number (a 0-d array), not a matrix")
    if len(shape) != 2:
        raise _refuse(label, f"holds an array of shape {tuple(int(n) for n in shape)}, "
                             "not a 2-D matrix")
    rows, cols = (int(n) for n in shape)
    if rows != cols or rows == 0:
        raise _refuse(label, f"is {rows} x {cols}; the matrix must be square and non-empty")
    return rows


def _dense_budget(n: int, label: str) -> None:
    need = n * n * 8
    if need > MAX_DENSE_BYTES:
        raise _refuse(label, f"a dense {n} x {n} matrix needs {need} bytes as float64, more "
                             f"than the {MAX_DENSE_BYTES} allowed; save a large matrix "
                             "as a sparse .npz or .mtx")


def _sparse_budget(n: int, nnz: int, label: str) -> None:
    if n > MAX_SPARSE_DIM:
        raise _refuse(label, f"a sparse {n} x {n} matrix is larger than the {MAX_SPARSE_DIM} "
                             "rows allowed")
    if nnz > MAX_SPARSE_NNZ:
        raise _refuse(label, f"{nnz} stored entries, more than the {MAX_SPARSE_NNZ} allowed")


def _npy_header(fh, label: str) -> tuple[tuple, np.dtype, int]:
    """``(shape, dtype, header end)`` of the .npy stream ``fh`` (no data is read)."""
    from numpy.lib import format as npf

    start = fh.tell()
    try:
        version = npf.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npf.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = npf.read_array_header_2_0(fh)
        else:
            raise _refuse(label, f".npy format version {version[0]}.{version[1]} is not "
                                 "supported (1.0 and 2.0 are)")
    except StepsafeError:
        raise
    except (ValueError, OSError, EOFError, SyntaxError, TypeError) as exc:
        raise _refuse(label, f"not a valid .npy array: {_first_line(exc)}") from None
    return tuple(shape), dtype, fh.tell() - start


def _entries(shape: tuple) -> int:
    count = 1
    for n in shape:
        count *= int(n)
    return count


def _check_data_size(shape: tuple, dtype: np.dtype, available: int, label: str) -> None:
    need = _entries(shape) * dtype.itemsize
    if need > available:
        raise _refuse(label, f"truncated: the header declares {need} bytes of data, the file "
                             f"holds {available}")


def _first_line(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text[:100]


def _as_float(array: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):  # float128 beyond float64: inf, refused as non-finite
        return np.asarray(array, dtype=np.float64)


def read_matrix(path: Path, label: str, sparse_ok: bool = False):
    """The matrix in ``path`` as a float64 ndarray, or as a scipy CSR matrix when the file is
    sparse and ``sparse_ok``. Errors name ``label`` (the file name as the user wrote it)."""
    suffix = path.suffix.lower()
    if suffix not in (".npy", ".npz", ".mtx"):
        # checked before opening: the suffix decides the reader
        raise _refuse(label, "use a .npy, .npz or .mtx file")
    with open_regular(path, MAX_FILE_BYTES, label) as fh:
        size = path.stat().st_size
        try:
            if suffix == ".npy":
                return _read_npy(fh, size, label)
            if suffix == ".npz":
                return _read_npz(fh, label, sparse_ok)
            return _read_mtx(fh, label, sparse_ok)
        except StepsafeError:
            raise
        except MemoryError:
            raise _refuse(label, "not enough memory to read the matrix") from None
        except Exception as exc:  # noqa: BLE001 - any reader failure is bad input here
            raise _refuse(label, f"cannot read: {_first_line(exc)}") from None


def _read_npy(fh, size: int, label: str) -> np.ndarray:
    from numpy.lib import format as npf

    shape, dtype, header = _npy_header(fh, label)
    check_dtype(dtype, label)
    _dense_budget(_square(shape, label), label)
    _check_data_size(shape, dtype, size - header, label)
    fh.seek(0)
    array = npf.read_array(fh, allow_pickle=False)
    return _as_float(array)


def _central_directory(fh) -> tuple[int, int] | None:
    """``(entries, bytes)`` of the zip central directory, from its end record (zip64 aware),
    or None if the stdlib helper is missing. zipfile.ZipFile would build one object per
    entry of a directory that can fill the whole file."""
    import zipfile

    end_record = getattr(zipfile, "_EndRecData", None)
    entries = getattr(zipfile, "_ECD_ENTRIES_TOTAL", None)
    size = getattr(zipfile, "_ECD_SIZE", None)
    if end_record is None or entries is None or size is None:
        return None
    record = end_record(fh)
    fh.seek(0)
    if not record:
        return None
    return int(record[entries]), int(record[size])


def _read_npz(fh, label: str, sparse_ok: bool):
    import zipfile

    directory = _central_directory(fh)
    if directory is not None and (directory[0] > MAX_NPZ_MEMBERS
                                  or directory[1] > MAX_NPZ_MEMBERS * 1024):
        raise _refuse(label, f"the .npz file holds {directory[0]} members in a "
                             f"{directory[1]}-byte directory, more than the {MAX_NPZ_MEMBERS} "
                             "allowed")
    try:
        archive = zipfile.ZipFile(fh)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError) as exc:
        raise _refuse(label, f"not a valid .npz (zip) file: {_first_line(exc)}") from None
    with archive:
        infos = archive.infolist()
        if not infos:
            raise _refuse(label, "the .npz file holds no arrays")
        if len(infos) > MAX_NPZ_MEMBERS:
            raise _refuse(label, f"the .npz file holds {len(infos)} members, more than the "
                                 f"{MAX_NPZ_MEMBERS} allowed")
        unpacked = sum(info.file_size for info in infos)
        if unpacked > MAX_FILE_BYTES:
            raise _refuse(label, f"the .npz file unpacks to {unpacked} bytes, more than the "
                                 f"{MAX_FILE_BYTES} allowed")
        members: dict[str, _Member] = {}
        for info in infos:
            if not info.filename.endswith(".npy") or info.is_dir():
                raise _refuse(label, f"the .npz member {info.filename[:60]!r} is not a .npy "
                                     "array")
            with archive.open(info) as stream:
                shape, dtype, header = _npy_header(stream, f"{label}[{info.filename}]")
            members[info.filename[:-4]] = _Member(info, shape, dtype, info.file_size - header)
        if "format" in members:
            return _read_sparse_npz(fh, archive, members, label, sparse_ok)
        if len(members) != 1:
            raise _refuse(label, f"holds {len(members)} arrays; save one")
        (member,) = members.values()
        check_dtype(member.dtype, label)
        _dense_budget(_square(member.shape, label), label)
        return _as_float(_member(archive, member, label))


class _Member(NamedTuple):
    info: zipfile.ZipInfo
    shape: tuple
    dtype: np.dtype
    available: int  # bytes after the .npy header


def _member(archive: zipfile.ZipFile, member: _Member, label: str) -> np.ndarray:
    """One member's array, once its header has passed the budgets."""
    from numpy.lib import format as npf

    _check_data_size(member.shape, member.dtype, member.available,
                     f"{label}[{member.info.filename}]")
    with archive.open(member.info) as stream:
        return npf.read_array(stream, allow_pickle=False)


def _read_sparse_npz(fh, archive, members: dict, label: str, sparse_ok: bool):
    import scipy.sparse as sp

    member = members["format"]
    if member.dtype.kind not in "SU" or _entries(member.shape) != 1 or \
            member.dtype.itemsize > 64:
        raise _refuse(label, "a sparse .npz needs format.npy holding one short name")
    fmt = _member(archive, member, label).reshape(()).item()
    fmt = fmt.decode("ascii", "replace") if isinstance(fmt, bytes) else str(fmt)
    if fmt not in _SPARSE_FORMATS:
        raise _refuse(label, f"unknown sparse format {fmt[:20]!r} (scipy.sparse.save_npz "
                             f"writes {', '.join(_SPARSE_FORMATS)})")
    if "shape" not in members or "data" not in members:
        raise _refuse(label, "a sparse .npz needs shape.npy and data.npy")
    member = members["shape"]
    if member.dtype.kind not in "iu" or tuple(member.shape) != (2,):
        raise _refuse(label, "shape.npy of a sparse .npz must hold two whole numbers")
    rows, cols = (int(n) for n in _member(archive, member, label))
    if rows < 0 or cols < 0:
        raise _refuse(label, f"negative shape {rows} x {cols}")
    n = _square((rows, cols), label)
    data = members["data"]
    check_dtype(data.dtype, label)
    _sparse_budget(n, _entries(data.shape), label)
    for name, member in members.items():
        if _entries(member.shape) > MAX_SPARSE_NNZ + MAX_SPARSE_DIM + 1:
            raise _refuse(label, f"{name}.npy has {_entries(member.shape)} entries, more than "
                                 f"a {n} x {n} matrix with {MAX_SPARSE_NNZ} entries needs")
        _check_data_size(member.shape, member.dtype, member.available, f"{label}[{name}.npy]")
    fh.seek(0)
    matrix = sp.load_npz(fh)
    if tuple(matrix.shape) != (n, n):
        raise _refuse(label, f"the arrays do not match the declared shape {n} x {n}")
    check_dtype(matrix.dtype, label)
    return _finish_sparse(matrix, n, label, sparse_ok)


def _finish_sparse(matrix: Any, n: int, label: str, sparse_ok: bool):
    import scipy.sparse as sp

    csr = sp.csr_matrix(matrix)
    csr.check_format(full_check=True)  # index arrays in range, before any other use
    with np.errstate(all="ignore"):
        csr = csr.astype(np.float64)
    if sparse_ok:
        return csr
    _dense_budget(n, label)
    return csr.toarray()


_MM_BANNER = re.compile(r"%%matrixmarket\s+matrix\s+(coordinate|array)\s+(\S+)\s+(\S+)\s*",
                        re.IGNORECASE | re.ASCII)
_MM_INT = re.compile(r"[0-9]{1,12}", re.ASCII)


def _read_mtx(fh, label: str, sparse_ok: bool):
    """A Matrix Market file, read by its definition (NIST): the banner, comment lines, the
    size line, then the entries, every field a plain number (``np.loadtxt``: ``1_000``,
    ``0x10`` or ``9abc`` are refused, never read by a prefix), each row with exactly the
    fields its format has, indices integers in range, and as many rows as declared."""
    import io

    banner = fh.readline(256).decode("ascii", "replace")
    match = _MM_BANNER.fullmatch(banner.strip())
    if match is None:
        raise _refuse(label, "not a Matrix Market file: the first line must be "
                             "'%%MatrixMarket matrix coordinate|array real|integer "
                             "general|symmetric'")
    fmt, field, symmetry = (g.lower() for g in match.groups())
    if field == "complex":
        raise _refuse(label, "complex values are not allowed: a stiffness, mass or Hessian "
                             "matrix is real (the real part is never taken silently)")
    if field == "pattern":
        raise _refuse(label, "a pattern matrix (positions without values) is not allowed; "
                             "write the values")
    if field not in _MM_REAL_FIELDS:
        raise _refuse(label, f"Matrix Market field {field[:20]!r} is not allowed; use real "
                             "or integer")
    if symmetry not in ("general", "symmetric"):
        raise _refuse(label, f"Matrix Market symmetry {symmetry[:20]!r} is not allowed: a "
                             "stiffness, mass or Hessian matrix is general or symmetric")
    line, comment_goes_on = 1, False
    while True:
        raw = fh.readline(1024)  # (a comment line longer than this is read in pieces)
        if not raw:
            raise _refuse(label, "no size line after the banner")
        if comment_goes_on:
            comment_goes_on = not raw.endswith(b"\n")
            continue
        line += 1
        text = raw.decode("ascii", "replace").strip()
        if text and not text.startswith("%"):
            break
        comment_goes_on = not raw.endswith(b"\n")
    sizes = text.split()
    want = 3 if fmt == "coordinate" else 2
    if len(sizes) != want or not all(_MM_INT.fullmatch(x) for x in sizes):
        raise _refuse(label, f"line {line}: the size line must be {want} integers, got "
                             f"{text[:60]!r}")
    rows, cols = int(sizes[0]), int(sizes[1])
    n = _square((rows, cols), label)
    if fmt == "coordinate":
        entries = int(sizes[2])
        _sparse_budget(n, entries * (1 if symmetry == "general" else 2), label)
        expected = (entries, 3)
    else:
        _dense_budget(n, label)
        entries = n * n if symmetry == "general" else n * (n + 1) // 2
        expected = (entries, 1)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "input contained no data"
        try:
            body = np.loadtxt(io.BytesIO(fh.read()), dtype=float, comments="%", ndmin=2,
                              encoding="ascii")
        except ValueError as exc:
            raise _refuse(label, f"an entry is not a plain number or a row has the wrong "
                                 f"number of fields: {_first_line(exc)}") from None
    if body.size == 0:
        body = body.reshape(0, expected[1])
    if body.shape != expected:
        raise _refuse(label, f"{body.shape[0]} rows of {body.shape[1]} fields, the header "
                             f"declares {expected[0]} of {expected[1]}")
    if not np.all(np.isfinite(body)):
        raise _refuse(label, "has a non-finite entry")
    values_column = body[:, -1]
    if field in ("integer", "unsigned-integer") and np.any(values_column
                                                           != np.floor(values_column)):
        raise _refuse(label, f"an entry of an {field} matrix is not an integer")
    if fmt == "array":
        values = body[:, 0]
        if symmetry == "general":
            return values.reshape(n, n, order="F").copy()
        dense = np.zeros((n, n))
        lower = np.tril_indices(n)
        order = np.lexsort((lower[0], lower[1]))  # column by column, as the format stores
        dense[lower[0][order], lower[1][order]] = values
        return dense + np.tril(dense, -1).T
    index = body[:, :2]
    if np.any(index != np.floor(index)) or np.any(index < 1) or np.any(index > n):
        raise _refuse(label, f"row and column indices must be integers from 1 to {n}")
    i, j, v = index[:, 0].astype(np.int64) - 1, index[:, 1].astype(np.int64) - 1, body[:, 2]
    if np.unique(i * n + j).size != i.size:
        # summing repeated entries in float64 can cancel what they mean (1e20 + 5000 -
        # 1e20 is 0): a matrix is written with each position once
        raise _refuse(label, "a position is given more than once; write each entry once")
    if symmetry == "symmetric":
        if np.any(j > i):
            raise _refuse(label, "a symmetric Matrix Market file stores the lower triangle "
                                 "only (row >= column)")
        off = i != j
        i, j, v = np.concatenate([i, j[off]]), np.concatenate([j, i[off]]), \
            np.concatenate([v, v[off]])
    import scipy.sparse as sp

    matrix = sp.coo_matrix((v, (i, j)), shape=(n, n))
    return _finish_sparse(matrix, n, label, sparse_ok)
