"""Content-keyed cache of numpy arrays in ``.npz`` files (no Blender dependency).

A cache file stores named arrays plus the key of the inputs that produced them and a format
version. ``load`` returns None for a missing or stale file (different key or version), so the
caller recomputes; a file that exists but cannot be read raises ``CacheCorrupt``. Files are
written atomically (temporary file in the same directory, then ``os.replace``), so a crash or a
concurrent reader never sees a half-written cache.
"""

import hashlib
import os
import tempfile
import zipfile

import numpy as np

FORMAT_VERSION = 1
_KEY_FIELD = "__cache_key__"
_VERSION_FIELD = "__cache_version__"


class CacheCorrupt(Exception):
    """A cache file exists but cannot be read; delete it and recompute."""


def content_key(*parts):
    """Hex digest (32 chars of sha256) identifying ``parts`` in order.

    Parts may be numpy arrays (hashed by dtype, shape and bytes), None, bool / int / float / str
    / bytes (hashed by type and repr), numpy scalars, or tuples / lists of these (recursively).
    """
    digest = hashlib.sha256()
    for part in parts:
        _hash_part(digest, part)
    return digest.hexdigest()[:32]


def _hash_part(digest, part):
    """Feed one part into digest with a type tag, so different values never collide by layout."""
    if isinstance(part, np.ndarray):
        if part.dtype.hasobject:  # bytes would be pointers, not content
            raise TypeError("cannot hash an object-dtype array into a cache key")
        array = np.ascontiguousarray(part)
        digest.update(f"ndarray:{array.dtype.str}:{array.shape}:".encode())
        digest.update(array.tobytes())
    elif isinstance(part, np.generic):
        _hash_part(digest, part.item())
    elif isinstance(part, (tuple, list)):
        digest.update(f"{type(part).__name__}:{len(part)}:".encode())
        for item in part:
            _hash_part(digest, item)
    elif part is None or isinstance(part, (bool, int, float, str, bytes)):
        text = repr(part).encode()
        digest.update(f"{type(part).__name__}:{len(text)}:".encode() + text)
    else:
        raise TypeError(f"cannot hash a {type(part).__name__} into a cache key")
    digest.update(b";")


def save(path, key, arrays):
    """Atomically write ``arrays`` (dict name -> array) with ``key`` to the ``.npz`` file ``path``.

    Parent directories are created. Arrays must not need pickling (no object dtype).
    """
    reserved = {_KEY_FIELD, _VERSION_FIELD} & set(arrays)
    if reserved:
        raise ValueError(f"array names {sorted(reserved)} are reserved by the cache")
    arrays = {name: np.asarray(a) for name, a in arrays.items()}
    pickled = sorted(name for name, a in arrays.items() if a.dtype.hasobject)
    if pickled:  # load() refuses pickles (allow_pickle=False), so never write them
        raise ValueError(f"arrays {pickled} have object dtype and cannot be cached")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp_path = tempfile.mkstemp(dir=folder, prefix=".tmp_", suffix=".npz")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **{_KEY_FIELD: np.array(str(key)), _VERSION_FIELD: np.array(FORMAT_VERSION)},
                     **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
    except BaseException:
        if os.path.exists(tmp_path):
            os.remove(tmp_path)
        raise


def load(path, key):
    """Arrays saved under ``key`` at ``path`` as a dict, or None if missing or stale.

    Raises CacheCorrupt if the file exists but is not a readable cache file.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        return None
    arrays = _read_npz(path)
    try:
        version, stored_key = int(arrays.pop(_VERSION_FIELD)), str(arrays.pop(_KEY_FIELD))
    except (KeyError, TypeError, ValueError) as exc:
        raise CacheCorrupt(f"cache file {path} is not an RS Elastic cache file") from exc
    if version != FORMAT_VERSION or stored_key != str(key):
        return None
    return arrays


def validate(arrays, schema, path=""):
    """Check loaded arrays against ``schema`` {name: (dtype kinds, shape)}; return the sizes.

    kinds is a string of numpy dtype kinds ("f", "iu", ...); a shape entry is an int (fixed), a
    str (a size that must agree wherever the same name appears) or None (any). Float arrays must
    be finite. Raises CacheCorrupt naming the first problem, so the caller rebuilds the file.
    """
    sizes = {}
    for name, (kinds, shape) in schema.items():
        if name not in arrays:
            raise CacheCorrupt(f"cache file {path} has no array '{name}'")
        a = arrays[name]
        if a.dtype.kind not in kinds or a.ndim != len(shape):
            raise CacheCorrupt(f"cache file {path}: array '{name}' is {a.dtype} {a.shape}")
        for axis, (want, got) in enumerate(zip(shape, a.shape)):
            if isinstance(want, str):
                want = sizes.setdefault(want, got)
            if want is not None and want != got:
                raise CacheCorrupt(f"cache file {path}: array '{name}' has shape {a.shape}")
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise CacheCorrupt(f"cache file {path}: array '{name}' is not finite")
    return sizes


def stored_key(path):
    """The key a cache file was saved under, reading nothing else; None if missing or unreadable."""
    try:
        with np.load(os.fspath(path), allow_pickle=False) as data:
            if int(data[_VERSION_FIELD]) != FORMAT_VERSION:
                return None
            return str(data[_KEY_FIELD])
    except Exception:  # missing, truncated or foreign: the caller treats it as "not this key"
        return None


def _read_npz(path):
    """Every array of the .npz at path as a dict; CacheCorrupt if it is not a readable .npz."""
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):  # a bare .npy is not ours
            raise ValueError("not an .npz archive")
        with data:
            # Read every member now, so truncated data fails here and not in the caller.
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise CacheCorrupt(f"cache file {path} is unreadable ({exc})") from exc
