"""Tests for solver.cache: content keys, round trip, staleness, corruption, atomic writes."""

import os

import numpy as np
import pytest

from solver import cache


def sample_arrays():
    rng = np.random.default_rng(0)
    return {"X": rng.normal(size=(10, 3)), "T": np.arange(16, dtype=np.int64).reshape(4, 4),
            "lam": np.linspace(1.0, 2.0, 5).astype(np.float32)}


def test_content_key_depends_on_every_part():
    X = np.arange(6.0).reshape(2, 3)
    key = cache.content_key(X, 1e6, 0.3, "mesh", (1, 2))
    assert len(key) == 32 and int(key, 16) >= 0
    assert key == cache.content_key(X.copy(), 1e6, 0.3, "mesh", (1, 2))
    variants = [
        cache.content_key(X + 1e-12, 1e6, 0.3, "mesh", (1, 2)),       # values
        cache.content_key(X.reshape(3, 2), 1e6, 0.3, "mesh", (1, 2)),  # shape
        cache.content_key(X.astype(np.float32), 1e6, 0.3, "mesh", (1, 2)),  # dtype
        cache.content_key(X, 1e6, 0.31, "mesh", (1, 2)),
        cache.content_key(X, 1e6, 0.3, "mesh", (2, 1)),                # order
        cache.content_key(X, 1e6, 0.3, "mesh", (1, 2), None),
        cache.content_key(X, 1000000, 0.3, "mesh", (1, 2)),            # int vs float
    ]
    assert len(set(variants + [key])) == len(variants) + 1
    assert cache.content_key("ab", "c") != cache.content_key("a", "bc")
    with pytest.raises(TypeError):
        cache.content_key(object())
    with pytest.raises(TypeError):
        cache.content_key(np.array([{}, 1], dtype=object))


def test_round_trip(tmp_path):
    path = tmp_path / "sub" / "dir" / "modes.npz"  # parents are created
    arrays = sample_arrays()
    cache.save(path, "key-1", arrays)
    loaded = cache.load(path, "key-1")
    assert set(loaded) == set(arrays)
    for name, array in arrays.items():
        assert loaded[name].dtype == array.dtype
        np.testing.assert_array_equal(loaded[name], array)


def test_missing_or_stale_file_returns_none(tmp_path, monkeypatch):
    path = tmp_path / "c.npz"
    assert cache.load(path, "key") is None
    cache.save(path, "old-key", sample_arrays())
    assert cache.load(path, "new-key") is None
    assert cache.load(path, "old-key") is not None
    monkeypatch.setattr(cache, "FORMAT_VERSION", cache.FORMAT_VERSION + 1)
    assert cache.load(path, "old-key") is None  # written by another format version


def test_garbage_file_raises_cache_corrupt(tmp_path):
    path = tmp_path / "garbage.npz"
    path.write_bytes(os.urandom(2000))
    with pytest.raises(cache.CacheCorrupt, match="garbage.npz"):
        cache.load(path, "key")
    path.write_bytes(b"")
    with pytest.raises(cache.CacheCorrupt):
        cache.load(path, "key")


def test_truncated_file_raises_cache_corrupt(tmp_path):
    path = tmp_path / "c.npz"
    cache.save(path, "key", sample_arrays())
    data = path.read_bytes()
    for cut in (len(data) // 2, len(data) - 30, 100):
        path.write_bytes(data[:cut])
        with pytest.raises(cache.CacheCorrupt):
            cache.load(path, "key")


def test_foreign_npz_raises_cache_corrupt(tmp_path):
    path = tmp_path / "foreign.npz"
    np.savez(path, a=np.arange(3))
    with pytest.raises(cache.CacheCorrupt, match="not an RS Elastic cache"):
        cache.load(path, "key")
    npy = tmp_path / "plain.npz"
    with open(npy, "wb") as f:
        np.save(f, np.arange(3))
    with pytest.raises(cache.CacheCorrupt):
        cache.load(npy, "key")


def test_save_is_atomic_and_leaves_no_temp_files(tmp_path, monkeypatch):
    path = tmp_path / "c.npz"
    cache.save(path, "key", sample_arrays())
    cache.save(path, "key2", {"a": np.ones(3)})  # overwrite
    assert sorted(os.listdir(tmp_path)) == ["c.npz"]
    assert set(cache.load(path, "key2")) == {"a"}

    # A failure while writing keeps the previous file intact and removes the temp file.
    def failing_savez(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(cache.np, "savez", failing_savez)
    with pytest.raises(OSError, match="disk full"):
        cache.save(path, "key3", {"b": np.zeros(2)})
    assert sorted(os.listdir(tmp_path)) == ["c.npz"]
    assert set(cache.load(path, "key2")) == {"a"}


def test_object_arrays_and_reserved_names_are_rejected(tmp_path):
    with pytest.raises(ValueError):
        cache.save(tmp_path / "c.npz", "key", {"__cache_key__": np.ones(1)})
    with pytest.raises(ValueError):
        cache.save(tmp_path / "c.npz", "key", {"obj": np.array([{}, 1], dtype=object)})
    assert os.listdir(tmp_path) == []


def test_validate_checks_presence_kind_shape_agreement_and_finiteness():
    schema = {"X": ("f", ("N", 3)), "T": ("iu", (None, 4)), "lam": ("f", ("N_lam",))}
    arrays = {"X": np.zeros((10, 3)), "T": np.zeros((4, 4), dtype=np.int64), "lam": np.ones(5)}
    assert cache.validate(arrays, schema) == {"N": 10, "N_lam": 5}
    agree = {"X": ("f", ("N", 3)), "Y": ("f", ("N",))}
    assert cache.validate({"X": np.zeros((4, 3)), "Y": np.zeros(4)}, agree) == {"N": 4}
    bad = [
        ({k: v for k, v in arrays.items() if k != "T"}, "has no array 'T'"),
        (dict(arrays, T=arrays["T"].astype(float)), "array 'T' is float64"),
        (dict(arrays, X=np.zeros((10, 2))), "array 'X' has shape"),
        (dict(arrays, lam=np.array([1.0, np.nan])), "array 'lam' is not finite"),
    ]
    for broken, message in bad:
        with pytest.raises(cache.CacheCorrupt, match=message):
            cache.validate(broken, schema)
    with pytest.raises(cache.CacheCorrupt, match="array 'Y' has shape"):
        cache.validate({"X": np.zeros((4, 3)), "Y": np.zeros(5)}, agree)
